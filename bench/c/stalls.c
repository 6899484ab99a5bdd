/*
 * Simulated host stalls on one CPU: a SCHED_FIFO 99 task that sleeps a random
 * GAP_MIN_MS..EVERY_MS ms, then holds the CPU for a random 0.5..MAX_MS ms, until it is
 * killed. Nothing below priority 99 runs on that CPU meanwhile, as nothing in a VM runs while
 * its host stalls it (docs/measurements.md, "The host's stalls"). With gaps of 100 ms and more
 * these are the rare long stalls of a throttled VM; with gaps of a few ms they are the steady
 * loss of a contended host, where every task of the VM runs several times slower.
 * scripts/under-stalls.sh runs a command (the test suite, say) with one on each CPU, to see
 * which tests a stalling machine breaks.
 *
 *   gcc -O2 -o stalls stalls.c
 *   ./stalls CPU MAX_MS EVERY_MS [GAP_MIN_MS [SEED]]     (GAP_MIN_MS: 100 if not given)
 */
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>

#include "rt_helpers.h"

int main(int argc, char **argv)
{
	if (argc < 4 || argc > 6) {
		fprintf(stderr, "usage: %s CPU MAX_MS EVERY_MS [GAP_MIN_MS [SEED]]\n", argv[0]);
		return 2;
	}
	int cpu = atoi(argv[1]);
	long max_us = atol(argv[2]) * 1000, every_ms = atol(argv[3]);
	long gap_min_ms = argc >= 5 ? atol(argv[4]) : 100;
	unsigned seed = argc == 6 ? (unsigned)atol(argv[5]) : (unsigned)cpu + 1;
	/* A gap at least twice the longest stall leaves the CPU to everything else at least
	 * half the time (and the kernel's real-time throttling out of play). */
	if (cpu < 0 || max_us < 1000 || gap_min_ms < 1 || every_ms < gap_min_ms ||
	    gap_min_ms * 1000 < 2 * max_us) {
		fprintf(stderr, "CPU must be >= 0, MAX_MS >= 1, GAP_MIN_MS >= 2 x MAX_MS and "
				"EVERY_MS >= GAP_MIN_MS\n");
		return 2;
	}
	if (on_cpu_fifo(cpu, 99) != 0)
		return 1;
	srand(seed);
	for (;;) {
		long gap_ms = gap_min_ms + rand() % (every_ms - gap_min_ms + 1);
		struct timespec d = { gap_ms / 1000, gap_ms % 1000 * 1000000L };
		nanosleep(&d, NULL);
		int64_t end = now_ns() + (500 + rand() % (max_us - 499)) * 1000LL;
		while (now_ns() < end)
			;
	}
}
