/*
 * Simulated host stalls on one CPU: a SCHED_FIFO 99 task that sleeps a random 100..EVERY_MS
 * ms, then holds the CPU for a random 0.5..MAX_MS ms, until it is killed. Nothing below
 * priority 99 runs on that CPU meanwhile, as nothing in a VM runs while its host stalls it
 * (docs/measurements.md, "The host's stalls"). scripts/under-stalls.sh runs a command (the
 * test suite, say) with one on each CPU, to see which tests a stalling machine breaks.
 *
 *   gcc -O2 -o stalls stalls.c
 *   ./stalls CPU MAX_MS EVERY_MS [SEED]
 */
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>

#include "rt_helpers.h"

int main(int argc, char **argv)
{
	if (argc < 4 || argc > 5) {
		fprintf(stderr, "usage: %s CPU MAX_MS EVERY_MS [SEED]\n", argv[0]);
		return 2;
	}
	int cpu = atoi(argv[1]);
	long max_us = atol(argv[2]) * 1000, every_ms = atol(argv[3]);
	unsigned seed = argc == 5 ? (unsigned)atol(argv[4]) : (unsigned)cpu + 1;
	if (cpu < 0 || max_us < 1000 || every_ms < 100) {
		fprintf(stderr, "CPU must be >= 0, MAX_MS >= 1 and EVERY_MS >= 100\n");
		return 2;
	}
	if (on_cpu_fifo(cpu, 99) != 0)
		return 1;
	srand(seed);
	for (;;) {
		long gap_ms = 100 + rand() % (every_ms - 99);
		struct timespec d = { gap_ms / 1000, gap_ms % 1000 * 1000000L };
		nanosleep(&d, NULL);
		int64_t end = now_ns() + (500 + rand() % (max_us - 499)) * 1000LL;
		while (now_ns() < end)
			;
	}
}
