#!/usr/bin/env python3
"""Reads RUNDIR/trace.mcap with the `mcap` package from PyPI (a reader drivelab did not
write) and checks it against the run's trace.csv, summary.json and scenario.toml:

- one /trace message per row of trace.csv, in order, every column equal (an empty or NaN
  cell is null), logged at t_k;
- with --wall: every recorded sample has its wall time, never decreasing;
- one /log message per supervisor event and per fault report, at its sample;
- with --services: per stage one /services message per second of the run, each covering
  a second of samples, the last (part) second included; with --cycle (real time) the plant's with its cycle latency;
- the metadata records `scenario` and `summary` equal scenario.toml and summary.json.

Usage: mcap_check.py RUNDIR [--wall] [--services] [--cycle]. Prints one line; exit 1 on a mismatch.
"""
import csv
import json
import math
import sys

from mcap.reader import make_reader


def fail(msg):
    print(f"mcap_check: FAIL: {msg}")
    sys.exit(1)


def ns(t_s):
    # As drivelab rounds: half away from zero (t >= 0).
    return int(math.floor(t_s * 1e9 + 0.5))


def same(cell, value):
    if cell == "" or cell.lower() == "nan":
        return value is None
    if value is None:
        return False
    return float(cell) == float(value)


def main():
    args = sys.argv[1:]
    run = [a for a in args if not a.startswith("--")][0]
    with open(f"{run}/trace.csv", newline="") as f:
        rows = csv.DictReader(f)
        columns = rows.fieldnames
        rows = list(rows)
    with open(f"{run}/summary.json") as f:
        summary = json.load(f)
    with open(f"{run}/scenario.toml") as f:
        scenario = f.read()
    fs = summary["rate_hz"]
    n_trace, last_wall, logs, seconds = 0, 0, [], {}
    with open(f"{run}/trace.mcap", "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema.encoding != "jsonschema" or channel.message_encoding != "json":
                fail(f"{channel.topic}: not JSON with a JSON schema")
            msg = json.loads(message.data)
            if channel.topic == "/trace":
                if n_trace >= len(rows):
                    fail(f"more /trace messages than the {len(rows)} rows of trace.csv")
                row = rows[n_trace]
                if set(msg) != set(columns) | {"t_wall_unix_ns"}:
                    fail(f"/trace fields {sorted(msg)} are not the columns {columns}")
                for c in columns:
                    if not same(row[c], msg[c]):
                        fail(f"row {n_trace} column {c}: csv {row[c]!r}, mcap {msg[c]!r}")
                if message.log_time != ns(float(row["t"])):
                    fail(f"row {n_trace}: log time {message.log_time} is not t_k")
                if "--wall" in args and int(row["plant_flags"]) & 64 == 0:
                    w = msg["t_wall_unix_ns"]
                    if w is None or w < last_wall:
                        fail(f"row {n_trace}: wall time {w} missing or before {last_wall}")
                    last_wall = w
                n_trace += 1
            elif channel.topic == "/log":
                logs.append((message.log_time, msg))
            elif channel.topic == "/services":
                seconds.setdefault(msg["service"], []).append((message.log_time, msg))
            else:
                fail(f"unexpected channel {channel.topic}")
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    if n_trace != len(rows) or n_trace != summary["samples"]:
        fail(f"{n_trace} /trace messages, {len(rows)} rows, {summary['samples']} samples")
    events, faults = summary["supervisor_events"], summary["faults"]
    want = [ns(e["k"] / fs) for e in events] + [ns(f["injected_k"] / fs) for f in faults]
    if [t for t, _ in logs] != want:
        fail(f"/log times {[t for t, _ in logs]} are not those of the events and faults {want}")
    if "--services" in args:
        stages = [s for p in summary["processes"].values() for s in p["stages"]]
        # Every second, the last one too, whole or not (it ends with the stage's last status).
        n_secs = math.ceil(summary["samples"] / fs)
        for st in stages:
            secs = seconds.get(st, [])
            if len(secs) != n_secs:
                fail(f"{st}: {len(secs)} /services messages for a run of {summary['samples'] / fs} s")
            if st == "plant" and secs[-1][1]["k_to"] != summary["samples"] - 1:
                fail(f"plant: the last /services message ends at sample {secs[-1][1]['k_to']}")
            # In real time every second has a rate, the first one too.
            if "--cycle" in args and any(not m["rate_hz"] > 0 for _, m in secs):
                fail(f"{st}: rates {[m['rate_hz'] for _, m in secs]}")
            # A second opens at (or just past) its first sample.
            starts = [int(m["k_from"] // fs) for _, m in secs]
            if starts != list(range(n_secs)):
                fail(f"{st}: not one message per second: seconds {starts}")
            for t, m in secs:
                if m["k_to"] <= m["k_from"] or t != ns(m["t_s"]) or m["samples"] <= 0:
                    fail(f"{st}: a second of samples {m['k_from']}..{m['k_to']} at {t}")
                # The cycle latency is the plant's, in real time only.
                if (m["cycle_us"] is None) == (st == "plant" and "--cycle" in args):
                    fail(f"{st}: cycle latency {m['cycle_us']}")
                if m["exec_us"] is None or m["exec_us"]["p99"] > m["exec_us"]["max"]:
                    fail(f"{st}: execution time {m['exec_us']}")
    if metadata.get("scenario", {}).get("scenario.toml") != scenario:
        fail("metadata 'scenario' is not scenario.toml")
    if json.loads(metadata.get("summary", {}).get("summary.json", "null")) != summary:
        fail("metadata 'summary' is not summary.json")
    n_sec = sum(len(v) for v in seconds.values())
    print(f"mcap_check: OK: {n_trace} samples equal trace.csv, {len(logs)} log entries, "
          f"{n_sec} service seconds, metadata {sorted(metadata)}")


main()
