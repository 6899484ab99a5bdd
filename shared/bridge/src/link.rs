//! Endpoints and Zenoh sessions: the drive's bridge listens (a Zenoh peer), the remote
//! tools connect (Zenoh clients). Multicast scouting and gossip are off on both sides, so a
//! session reaches exactly the endpoint it was given and announces itself to nobody.

use anyhow::{anyhow, Result};
use std::path::Path;
use zenoh::Wait;

/// Port of `drivelab run --zenoh-listen` without an endpoint (Zenoh's own default port).
pub const DEFAULT_PORT: u16 = 7447;
/// Endpoint of `drivelab run --zenoh-listen` without an endpoint: this machine only.
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7447";

/// Checks an endpoint of the form `tcp/HOST:PORT` or `tls/HOST:PORT` (HOST a name, an IPv4
/// address or a bracketed IPv6 address; PORT 1-65535 for a connection, 0-65535 for a
/// listener, 0 meaning any free port). Returns it unchanged, or a one-line error naming the
/// problem.
pub fn check_endpoint(ep: &str, listen: bool) -> Result<String, String> {
    let (proto, addr) = ep.split_once('/').ok_or_else(|| {
        format!("endpoint '{ep}' must be PROTOCOL/HOST:PORT, e.g. {DEFAULT_LISTEN}")
    })?;
    if !matches!(proto, "tcp" | "tls") {
        return Err(format!(
            "endpoint '{ep}': protocol '{proto}' is not built in (tcp or tls)"
        ));
    }
    let (host, port) = addr
        .rsplit_once(':')
        .ok_or_else(|| format!("endpoint '{ep}' has no port (PROTOCOL/HOST:PORT)"))?;
    let port: u16 = port
        .parse()
        .map_err(|_| format!("endpoint '{ep}': port '{port}' is not a number from 0 to 65535"))?;
    if port == 0 && !listen {
        return Err(format!("endpoint '{ep}': port 0 can only listen"));
    }
    let host_ok = if let Some(v6) = host.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
        v6.parse::<std::net::Ipv6Addr>().is_ok()
    } else {
        !host.is_empty()
            && host
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '.' || c == '-')
    };
    if !host_ok {
        return Err(format!(
            "endpoint '{ep}': '{host}' is not a host name or address"
        ));
    }
    ep.parse::<zenoh::config::EndPoint>()
        .map_err(|e| format!("endpoint '{ep}': {e}"))?;
    Ok(ep.to_string())
}

/// Checks, before a drive creates anything, that a listener endpoint (already checked by
/// [`check_endpoint`]) can be had: its address is this machine's and its port is free; returns
/// the endpoint to listen on. Port 0 (any free port) is replaced by a port that is free now,
/// so that the drive reports the port its bridge listens on, which the other side needs. The
/// check binds the port and lets it go at once, so another program may still take it before
/// the bridge does; then the bridge's own error says so. A host name that does not resolve
/// is left to the bridge.
pub fn check_free(ep: &str) -> Result<String, String> {
    use std::net::{TcpListener, ToSocketAddrs};
    let Some((proto, addr)) = ep.split_once('/') else {
        return Ok(ep.to_string());
    };
    let Ok(addrs) = addr.to_socket_addrs() else {
        return Ok(ep.to_string());
    };
    // Port 0: the port the first address got, for every address.
    let mut taken = None;
    for mut a in addrs {
        if let Some(p) = taken {
            a.set_port(p);
        }
        match TcpListener::bind(a) {
            Ok(l) if a.port() == 0 => {
                let got = l
                    .local_addr()
                    .map_err(|e| format!("endpoint '{ep}': cannot listen on {a}: {e}"))?;
                taken = Some(got.port());
            }
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AddrInUse => {
                return Err(format!(
                    "endpoint '{ep}': {a} is in use (another drive's bridge or a Zenoh router?); choose another port"
                ))
            }
            Err(e) if e.kind() == std::io::ErrorKind::AddrNotAvailable => {
                return Err(format!("endpoint '{ep}': {a} is not an address of this machine"))
            }
            Err(e) => return Err(format!("endpoint '{ep}': cannot listen on {a}: {e}")),
        }
    }
    Ok(match taken {
        Some(p) => {
            let host = addr.rsplit_once(':').map_or(addr, |(h, _)| h);
            format!("{proto}/{host}:{p}")
        }
        None => ep.to_string(),
    })
}

/// Which side of a link a session is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// The drive's bridge: a Zenoh peer listening on the endpoint.
    Listen,
    /// A remote tool: a Zenoh client connecting to the endpoint.
    Connect,
}

/// The Zenoh configuration of one side: `file` (a Zenoh JSON5 configuration, for TLS and
/// access control; see docs/remote.md) if given, else Zenoh's defaults; then the mode, the
/// endpoint and no scouting.
pub fn config(side: Side, endpoint: &str, file: Option<&Path>) -> Result<zenoh::Config> {
    let mut c = match file {
        Some(p) => zenoh::Config::from_file(p)
            .map_err(|e| anyhow!("{}", config_error(&p.display().to_string(), &e.to_string())))?,
        None => zenoh::Config::default(),
    };
    let set = |c: &mut zenoh::Config, key: &str, value: &str| {
        c.insert_json5(key, value)
            .map_err(|e| anyhow!("zenoh config {key}: {e}"))
    };
    let eps = format!("[\"{endpoint}\"]");
    match side {
        Side::Listen => {
            set(&mut c, "mode", "\"peer\"")?;
            set(&mut c, "listen/endpoints", &eps)?;
            set(&mut c, "connect/endpoints", "[]")?;
        }
        Side::Connect => {
            set(&mut c, "mode", "\"client\"")?;
            set(&mut c, "connect/endpoints", &eps)?;
            set(&mut c, "listen/endpoints", "[]")?;
        }
    }
    set(&mut c, "scouting/multicast/enabled", "false")?;
    set(&mut c, "scouting/gossip/enabled", "false")?;
    Ok(c)
}

/// Reads Zenoh configuration file `file` as [`config`] will, so that a run can refuse a bad
/// one before it makes anything.
pub fn check_config(file: &Path) -> Result<()> {
    config(Side::Listen, "tcp/127.0.0.1:7447", Some(file)).map(|_| ())
}

/// Opens a session; the error names the endpoint and Zenoh's reason on one line.
pub fn open(side: Side, endpoint: &str, file: Option<&Path>) -> Result<zenoh::Session> {
    let c = config(side, endpoint, file)?;
    zenoh::open(c).wait().map_err(|e| {
        let what = match side {
            Side::Listen => "listen on",
            Side::Connect => "connect to",
        };
        let text = e.to_string();
        // Zenoh says the same whether nothing answered or something that is not Zenoh did.
        let why = match (side, tidy(&text).starts_with("Unable to connect to any of")) {
            (Side::Connect, true) if tcp_answers(endpoint) => format!(
                "something accepted a TCP connection at {endpoint} but did not answer as Zenoh (another service's port? a drive listens with --zenoh-listen)"
            ),
            _ => reason(&text),
        };
        anyhow!("cannot {what} {endpoint}: {why}")
    })
}

/// True when a plain TCP connection to `tcp/HOST:PORT` is accepted within a second.
fn tcp_answers(endpoint: &str) -> bool {
    use std::net::ToSocketAddrs;
    let Some(addr) = endpoint.strip_prefix("tcp/") else {
        return false;
    };
    // An endpoint may carry Zenoh's options after '#' or '?'.
    let addr = addr.split(['#', '?']).next().unwrap_or(addr);
    addr.to_socket_addrs().into_iter().flatten().any(|a| {
        std::net::TcpStream::connect_timeout(&a, std::time::Duration::from_secs(1)).is_ok()
    })
}

/// Zenoh's reason for a session it could not open, in words: [`tidy`], and its "Unable to
/// connect to any of Single(…)" (nothing answered at the endpoint) said plainly.
fn reason(text: &str) -> String {
    let text = tidy(text);
    if text.starts_with("Unable to connect to any of") {
        "nothing accepted the connection there (is a drive listening, started with \
         --zenoh-listen on that address?)"
            .to_string()
    } else {
        text
    }
}

/// Zenoh's error about configuration file `file` in one line: a JSON5 error, which Zenoh
/// gives in its debug form (`JSON error: Message { msg: "…", location: Some(Location {
/// line: 1, column: 64 }) }`), as `FILE:LINE:COLUMN: message`; anything else tidied.
fn config_error(file: &str, text: &str) -> String {
    let text = tidy(text);
    let msg = text
        .split_once("msg: \"")
        .and_then(|(_, rest)| rest.split_once("\", location: "));
    let Some((msg, location)) = msg else {
        return format!("zenoh config {file}: {text}");
    };
    let number = |key: &str| -> Option<&str> {
        let after = location.split_once(key)?.1;
        let end = after
            .find(|c: char| !c.is_ascii_digit())
            .unwrap_or(after.len());
        Some(&after[..end]).filter(|d| !d.is_empty())
    };
    let msg = msg.replace("\\\"", "\"");
    match (number("line: "), number("column: ")) {
        (Some(l), Some(c)) => format!("zenoh config {file}:{l}:{c}: {msg}"),
        _ => format!("zenoh config {file}: {msg}"),
    }
}

/// Zenoh's error text on one line, without the source locations it appends (" at
/// /path/file.rs:12.") and the brackets around nested errors.
pub fn tidy(text: &str) -> String {
    let mut out = String::new();
    let mut rest = text;
    while let Some(i) = rest.find(" at /") {
        out.push_str(&rest[..i]);
        let tail = &rest[i + 4..];
        // The location ends at ".rs:LINE" and an optional '.'.
        match tail.find(".rs:") {
            Some(j) => {
                let after = &tail[j + 4..];
                let digits = after
                    .find(|c: char| !c.is_ascii_digit())
                    .unwrap_or(after.len());
                rest = after[digits..]
                    .strip_prefix('.')
                    .unwrap_or(&after[digits..]);
            }
            None => {
                out.push_str(" at ");
                rest = tail;
            }
        }
    }
    out.push_str(rest);
    let out = out.replace(['\n', '[', ']'], " ");
    out.split_whitespace().collect::<Vec<_>>().join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_are_checked_with_one_line_errors() {
        for ok in [
            "tcp/127.0.0.1:7447",
            "tcp/[::1]:7447",
            "tls/drive-1.lab:7447",
            "tcp/0.0.0.0:0",
        ] {
            assert_eq!(check_endpoint(ok, true).as_deref(), Ok(ok));
        }
        let err = |ep: &str, listen| check_endpoint(ep, listen).unwrap_err();
        assert_eq!(
            err("127.0.0.1:7447", true),
            "endpoint '127.0.0.1:7447' must be PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447"
        );
        assert_eq!(
            err("udp/127.0.0.1:7447", true),
            "endpoint 'udp/127.0.0.1:7447': protocol 'udp' is not built in (tcp or tls)"
        );
        assert_eq!(
            err("tcp/127.0.0.1", true),
            "endpoint 'tcp/127.0.0.1' has no port (PROTOCOL/HOST:PORT)"
        );
        assert_eq!(
            err("tcp/127.0.0.1:99999", true),
            "endpoint 'tcp/127.0.0.1:99999': port '99999' is not a number from 0 to 65535"
        );
        assert_eq!(
            err("tcp/127.0.0.1:0", false),
            "endpoint 'tcp/127.0.0.1:0': port 0 can only listen"
        );
        assert_eq!(
            err("tcp/bad host:1", false),
            "endpoint 'tcp/bad host:1': 'bad host' is not a host name or address"
        );
        assert!(err("tcp/[::zz]:1", false).contains("is not a host name"));
        for e in ["", "tcp/", "tcp/:7447"] {
            assert!(!err(e, true).contains('\n'), "{e}");
        }
    }

    #[test]
    fn a_listener_port_in_use_or_an_address_elsewhere_is_refused() {
        let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = taken.local_addr().unwrap().port();
        let ep = format!("tcp/127.0.0.1:{port}");
        assert_eq!(
            check_free(&ep).unwrap_err(),
            format!("endpoint '{ep}': 127.0.0.1:{port} is in use (another drive's bridge or a Zenoh router?); choose another port")
        );
        drop(taken);
        assert_eq!(check_free(&ep), Ok(ep.clone()));
        // TEST-NET-1 (RFC 5737) is no machine's own address.
        assert_eq!(
            check_free("tcp/192.0.2.1:7447").unwrap_err(),
            "endpoint 'tcp/192.0.2.1:7447': 192.0.2.1:7447 is not an address of this machine"
        );
        // Port 0: a port that was free, which the drive then reports.
        let any = check_free("tcp/127.0.0.1:0").unwrap();
        let port: u16 = any
            .strip_prefix("tcp/127.0.0.1:")
            .and_then(|p| p.parse().ok())
            .unwrap_or_else(|| panic!("{any}"));
        assert_ne!(port, 0);
        std::net::TcpListener::bind(("127.0.0.1", port)).expect("the port it chose is free");
        // The host stays as given.
        let named = check_free("tcp/localhost:0").unwrap();
        assert!(
            named.starts_with("tcp/localhost:") && !named.ends_with(":0"),
            "{named}"
        );
    }

    /// A port where a plain TCP service listens, told apart from one where nothing does.
    #[test]
    fn a_tcp_service_that_is_not_zenoh_is_told_from_no_listener() {
        let other = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = other.local_addr().unwrap().port();
        assert!(tcp_answers(&format!("tcp/127.0.0.1:{port}")));
        drop(other);
        assert!(!tcp_answers(&format!("tcp/127.0.0.1:{port}")));
        assert!(!tcp_answers("udp/127.0.0.1:7447"));
        let e = open(Side::Connect, &format!("tcp/127.0.0.1:{port}"), None).unwrap_err();
        assert!(
            e.to_string()
                .contains("nothing accepted the connection there"),
            "{e}"
        );
    }

    #[test]
    fn zenoh_errors_lose_their_source_locations() {
        let e = "Can not create a new TCP listener bound to tcp/127.0.0.1:40359: [127.0.0.1:40359: Address already in use (os error 98) at /root/.cargo/registry/src/x/zenoh-link-commons-1.10.2/src/tcp.rs:61.] at /root/y/unicast.rs:338.";
        assert_eq!(
            tidy(e),
            "Can not create a new TCP listener bound to tcp/127.0.0.1:40359: 127.0.0.1:40359: Address already in use (os error 98)"
        );
        assert_eq!(
            tidy("Unable to connect to any of [Single(tcp/127.0.0.1:1)]!  at /a/orchestrator.rs:447."),
            "Unable to connect to any of Single(tcp/127.0.0.1:1) !"
        );
        assert_eq!(
            reason("Unable to connect to any of [Single(tcp/127.0.0.1:1)]!  at /a/orchestrator.rs:447."),
            "nothing accepted the connection there (is a drive listening, started with \
             --zenoh-listen on that address?)"
        );
        assert_eq!(reason(e), tidy(e));
        assert_eq!(
            config_error(
                "extra.json5",
                "JSON error: Message { msg: \"unknown field `bogus_key`, expected one of `id`, `mode`\", location: Some(Location { line: 1, column: 64 }) }"
            ),
            "zenoh config extra.json5:1:64: unknown field `bogus_key`, expected one of `id`, `mode`"
        );
        assert_eq!(
            config_error("c.json5", "no such file"),
            "zenoh config c.json5: no such file"
        );
        // Zenoh's own error for a key it does not know, through `config`.
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("extra.json5");
        std::fs::write(&f, "{\n  bogus_key: 1,\n}\n").unwrap();
        let e = config(Side::Connect, "tcp/127.0.0.1:7447", Some(&f))
            .unwrap_err()
            .to_string();
        let want = format!("zenoh config {}:2:", f.display());
        assert!(
            e.starts_with(&want)
                && e.contains(": unknown field `bogus_key`")
                && !e.contains("Message {"),
            "{e}"
        );
    }

    #[test]
    fn a_listener_is_a_peer_and_a_connector_a_client_without_scouting() {
        let c = config(Side::Listen, DEFAULT_LISTEN, None).unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"peer\"");
        assert_eq!(
            c.get_json("listen/endpoints").unwrap().replace(' ', ""),
            "[\"tcp/127.0.0.1:7447\"]"
        );
        assert_eq!(c.get_json("scouting/multicast/enabled").unwrap(), "false");
        let c = config(Side::Connect, "tcp/10.0.0.2:7447", None).unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"client\"");
        let e = config(
            Side::Connect,
            "tcp/10.0.0.2:7447",
            Some(Path::new("/no/such.json5")),
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("zenoh config /no/such.json5:"), "{e}");
        // A malformed file: Zenoh's reason, without its source location.
        let bad = std::env::temp_dir().join(format!("drivelab-zcfg-{}.json5", std::process::id()));
        std::fs::write(&bad, "this is {{{ not json5").unwrap();
        let e = check_config(&bad).unwrap_err().to_string();
        let _ = std::fs::remove_file(&bad);
        assert!(
            e.starts_with(&format!("zenoh config {}:", bad.display()))
                && !e.contains(".rs:")
                && !e.contains('\n'),
            "{e}"
        );
    }
}
