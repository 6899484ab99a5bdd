#!/usr/bin/env python3
"""Whether a latency's tail comes back at a fixed period: which samples make the top 1 %.

    phase_of_tail.py CSV COLUMN RATE_HZ [PERIOD_MS]

CSV has a column `k` (the sample index) and COLUMN (µs after t_k): a drive's `timing.csv`
(`drivelab run --timing-csv`, COLUMN `command_published_us`: the cycle) or the output of
`bench/c/timer_phase.c` (`done_us`). Samples later than a period (a stall and its catch-up)
are left out. Prints the p50 and p99; for periods of 1, 2, 4, 5, 10 and 20 ms, the share of
the top 1 % that falls on one phase (k mod the samples in a period); then for PERIOD_MS (by
default the period whose phase holds the most above an even spread) that phase, how its
samples and their neighbours fare, the p99 without them, and second by second which phase
led: an interruption at a fixed rate in another clock drifts across the samples. docs/measurements.md, "A 100 Hz interruption".
"""
import collections
import csv
import sys


def q(v, p):
    v = sorted(v)
    return v[min(len(v) - 1, int(p * len(v)))]


def main():
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__.strip().splitlines()[2].strip())
    path, col, rate = sys.argv[1], sys.argv[2], float(sys.argv[3])
    if rate <= 0:
        sys.exit("RATE_HZ must be positive")
    ts_us = 1e6 / rate
    rows = []
    with open(path) as f:
        for r in csv.DictReader(f):
            if r.get(col):
                v = float(r[col])
                if v < ts_us:
                    rows.append((int(r["k"]), v))
    if len(rows) < 100:
        sys.exit(f"{path}: {len(rows)} samples with {col} under a period; need 100")
    vals = [v for _, v in rows]
    p99 = q(vals, 0.99)
    print(f"{path}: {len(rows)} samples, {col} p50 {q(vals, .5):.1f} µs, p99 {p99:.1f} µs")
    best = None
    shares = []
    for ms in (1, 2, 4, 5, 10, 20):
        m = round(rate * ms / 1000)
        if m < 2:
            continue
        c = collections.Counter(k % m for k, v in rows if v >= p99)
        share = c.most_common(1)[0][1] / sum(c.values())
        shares.append(f"{ms} ms {100 * share:.0f} %")
        if best is None or share - 1 / m > best[1]:
            best = (ms, share - 1 / m)
    print("top 1 % on one phase:", ", ".join(shares))
    period_ms = float(sys.argv[4]) if len(sys.argv) == 5 else best[0]
    n = round(rate * period_ms / 1000)
    if n < 2:
        sys.exit("RATE_HZ and PERIOD_MS must give at least 2 samples a period")
    tail = collections.Counter(k % n for k, v in rows if v >= p99)
    phase, count = tail.most_common(1)[0]
    total = sum(tail.values())
    print(f"top 1 % ({total} samples) by k mod {n} ({period_ms:g} ms): phase {phase} holds "
          f"{count} ({100 * count / total:.0f} %; {100 / n:.1f} % if spread evenly)")
    for label, d in (("phase - 1", -1), ("phase", 0), ("phase + 1", 1)):
        v = [x for k, x in rows if k % n == (phase + d) % n]
        print(f"  {label:9s} p50 {q(v, .5):6.1f}  p90 {q(v, .9):6.1f}  p99 {q(v, .99):6.1f} µs")
    rest = [x for k, x in rows if k % n != phase]
    print(f"p99 without the phase's samples: {q(rest, .99):.1f} µs")
    per = collections.defaultdict(collections.Counter)
    for k, v in rows:
        if v >= p99:
            per[int(k / rate)][k % n] += 1
    lead = []
    for s in sorted(per):
        ph, c = per[s].most_common(1)[0]
        lead.append(f"{s}:{ph}({c})")
    print("second: leading phase (its top-1 % samples):", " ".join(lead))


if __name__ == "__main__":
    main()
