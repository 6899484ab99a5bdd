#!/usr/bin/env python3
"""What core 1 was doing at each of the plant's deadlines, from a perf trace of a drive.

Record a running drive (root; all CPUs, because this kernel drops the events of an idle
CPU when perf watches only that CPU), then run this on the text dump:

    perf record -k CLOCK_MONOTONIC -a -o drive.data \
        -e sched:sched_switch,sched:sched_wakeup,timer:hrtimer_start -- sleep 3
    perf script --ns -i drive.data > drive.txt
    python3 bench/tools/perf_at_deadline.py drive.txt PLANT_PID [CPU]

(Start perf pinned to another CPU, `taskset -c 0 perf record ...`, or perf's own process
shows up on the measured CPU and pushes other tasks over to it.)

The deadlines are the expiry times of the plant's own `clock_nanosleep` timers
(`hrtimer_start` by the plant's pid, function `hrtimer_wakeup`). For each, the task on the
CPU at that instant is the one the last switch before it put there ("idle" after a switch
to the idle task), and the delay is deadline → the plant's first wake-up of another task
(its publish of the measurement). Prints the delay's percentiles by that state, how many
deadlines were later than half and 90 % of a period by that state (the ones that cost
samples), and every task's time on the CPU, switches per period and longest single run.
docs/measurements.md, "Where the chain's tail is not" and "Who holds the drive's core".
"""
import bisect
import re
import sys
from collections import defaultdict

LINE = re.compile(r'^\s*(.+?)\s+(\d+)\s+\[(\d+)\]\s+(\d+)\.(\d+):\s+(\S+):\s*(.*)$')
KV = re.compile(r'(\w+)=(\S+)')


def pct(v, p):
    v = sorted(v)
    return v[min(len(v) - 1, int(p / 100 * len(v)))] / 1e3 if v else float('nan')


def main():
    if len(sys.argv) < 3:
        sys.exit('usage: perf_at_deadline.py PERF_SCRIPT_TXT PLANT_PID [CPU]')
    path, plant = sys.argv[1], int(sys.argv[2])
    cpu = int(sys.argv[3]) if len(sys.argv) > 3 else 1
    events, deadlines = [], []
    on_cpu, comms, switches = defaultdict(int), {}, defaultdict(int)
    longest = defaultdict(int)
    cur, since = None, 0
    for ln in open(path):
        m = LINE.match(ln)
        if not m or int(m.group(3)) != cpu:
            continue
        _, pid, _, s, ns, ev, rest = m.groups()
        pid, t = int(pid), int(s) * 1_000_000_000 + int(ns.ljust(9, '0')[:9])
        kv = dict(KV.findall(rest))
        events.append((t, pid, ev, kv))
        if ev == 'timer:hrtimer_start' and pid == plant and kv.get('function') == 'hrtimer_wakeup':
            deadlines.append(int(kv['expires']))
        elif ev == 'sched:sched_switch':
            nxt = int(kv['next_pid'])
            comms[nxt] = kv['next_comm']
            if cur is not None:
                on_cpu[cur] += t - since
                longest[cur] = max(longest[cur], t - since)
            switches[pid] += 1
            cur, since = nxt, t
    if not events or not deadlines:
        sys.exit(f'no events of pid {plant} on cpu {cpu} in {path}')
    times = [e[0] for e in events]
    by_state = defaultdict(list)
    for d in deadlines:
        i = bisect.bisect_left(times, d)
        if i == 0 or i >= len(events):
            continue
        _, pid, ev, kv = events[i - 1]
        if ev == 'sched:sched_switch':
            nxt = kv['next_comm']
            state = 'idle' if nxt.startswith('swapper') else f"{nxt} ({kv['next_pid']})"
        else:
            state = f'{comms.get(pid, "?")} ({pid})'
        j = i
        while j < len(events) and not (events[j][1] == plant and events[j][2] == 'sched:sched_wakeup'):
            j += 1
        if j < len(events):
            by_state[state].append(events[j][0] - d)
    every = [x for v in by_state.values() for x in v]
    print(f'{len(every)} deadlines; deadline -> the plant wakes the next stage, us:')
    print(f'  all: p50 {pct(every, 50):.1f}  p99 {pct(every, 99):.1f}  p99.9 {pct(every, 99.9):.1f}')
    top = sorted(every)[int(0.99 * len(every))] if every else 0
    for state, v in sorted(by_state.items(), key=lambda x: -len(x[1])):
        tail = sum(1 for x in v if x >= top)
        print(f'  at the deadline {state}: {len(v)} ({100 * len(v) / len(every):.2f} %), '
              f'p50 {pct(v, 50):.1f}  p99 {pct(v, 99):.1f}, in the slowest 1 %: {tail}')
    period = sorted(b - a for a, b in zip(deadlines, deadlines[1:]))[len(deadlines) // 2] \
        if len(deadlines) > 1 else 1
    # The deadlines late enough to cost a sample once the chain's own hops are added.
    for frac in (0.5, 0.9):
        late = {s: sum(1 for x in v if x > frac * period) for s, v in by_state.items()}
        named = ', '.join(f'{s} {n}' for s, n in sorted(late.items(), key=lambda x: -x[1]) if n)
        print(f'  later than {frac * period / 1e3:.0f} us ({frac:.0%} of the period): '
              f'{sum(late.values())}, by the task at the deadline: {named or "-"}')
    periods = (times[-1] - times[0]) / period
    print('time on the cpu, switches out per period, and the longest single run:')
    for p in sorted(on_cpu, key=lambda p: -on_cpu[p])[:10]:
        print(f'  {comms.get(p, "?"):20s} {p:7d}  {on_cpu[p] / periods / 1e3:6.2f} us  '
              f'{switches[p] / periods:5.2f}  {longest[p] / 1e3:8.1f} us')


if __name__ == '__main__':
    main()
