#!/usr/bin/env bash
# Makes a private certificate authority and three certificates for the Zenoh TLS example
# (docs/remote.md): the drive's (CN=drive, for localhost and 127.0.0.1 plus any names
# given), an operator's workstation (CN=operator: may inject faults) and a viewer's
# (CN=viewer: may watch and record only). For a lab, not for production: keep ca-key.pem
# off the drive.
#
# Usage: scripts/zenoh-certs.sh DIR [DRIVE_NAME_OR_IP ...]
set -euo pipefail
dir=${1:?usage: scripts/zenoh-certs.sh DIR [DRIVE_NAME_OR_IP ...]}
shift
mkdir -p "$dir"
cd "$dir"
san="DNS:localhost,IP:127.0.0.1"
for n in "$@"; do
    if [[ $n =~ ^[0-9.]+$ || $n == *:* ]]; then san+=",IP:$n"; else san+=",DNS:$n"; fi
done
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 365 \
    -subj "/CN=drivelab lab CA" -keyout ca-key.pem -out ca.pem 2>/dev/null
make_cert() { # name extendedKeyUsage subjectAltName
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes \
        -subj "/CN=$1" -keyout "$1-key.pem" -out "$1.csr" 2>/dev/null
    printf 'basicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=%s\nsubjectAltName=%s\n' \
        "$2" "$3" >"$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days 365 \
        -extfile "$1.ext" -out "$1.pem" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
}
make_cert drive serverAuth,clientAuth "$san"
make_cert operator clientAuth "DNS:operator"
make_cert viewer clientAuth "DNS:viewer"
chmod 600 ./*-key.pem
echo "certificates in $(pwd): ca.pem, drive.pem, operator.pem, viewer.pem (keys *-key.pem)"
