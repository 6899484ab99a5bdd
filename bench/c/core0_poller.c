/*
 * Load on core 0 while bench/c/timer_chain.c measures core 1: a loop that sleeps
 * PERIOD_US (relative nanosleep, SCHED_OTHER) and wakes again, as the drive's recorder
 * thread polls its subscriptions (about 4 500 wake-ups per second), or spins when
 * PERIOD_US is 0. Runs until killed. docs/measurements.md, "Where the chain's tail is not".
 *
 *   gcc -O2 -o core0_poller core0_poller.c
 *   ./core0_poller PERIOD_US &  ./timer_chain 10000 3 0 0;  kill %1
 */
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

int main(int argc, char **argv)
{
	if (argc != 2) {
		fprintf(stderr, "usage: %s PERIOD_US (0: spin)\n", argv[0]);
		return 2;
	}
	cpu_set_t c;
	CPU_ZERO(&c);
	CPU_SET(0, &c);
	if (sched_setaffinity(0, sizeof c, &c) != 0)
		perror("sched_setaffinity");
	long us = atol(argv[1]);
	struct timespec t = { us / 1000000, (us % 1000000) * 1000 };
	volatile unsigned long x = 0;
	for (;;) {
		if (us > 0)
			nanosleep(&t, NULL);
		else
			for (int i = 0; i < 1000; i++)
				x++;
	}
}
