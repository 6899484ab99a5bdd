/*
 * Which samples a machine's periodic interruptions hit: a SCHED_FIFO 70 timer thread on
 * CPU 1 (absolute clock_nanosleep, memory locked, a CPU wake-up latency request of 0 held
 * on /dev/cpu_dma_latency) wakes RATE_HZ times a second for SECONDS, then stays on the CPU
 * for BUSY_US µs (0: it sleeps again at once), as a chain would. With TICK_AFTER_US its
 * deadlines sit that many µs before each whole millisecond of CLOCK_MONOTONIC, where this
 * kernel's scheduler tick fires (CONFIG_HZ 100, 250 or 1000), so that the tick lands that
 * long after a deadline; without it they start 2 ms from now, anywhere (as cyclictest's).
 * Prints one line per sample, "k,woke_us,done_us" (µs after t_k: its wake-up, the end of
 * its busy stretch), for bench/tools/phase_of_tail.py. docs/measurements.md, "The tick
 * inside a sample".
 *
 *   gcc -O2 -o timer_phase timer_phase.c
 *   ./timer_phase RATE_HZ SECONDS BUSY_US [TICK_AFTER_US] > phase.csv
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <time.h>
#include <unistd.h>

#include "rt_helpers.h"

int main(int argc, char **argv)
{
	if (argc != 4 && argc != 5) {
		fprintf(stderr, "usage: %s RATE_HZ SECONDS BUSY_US [TICK_AFTER_US]\n", argv[0]);
		return 2;
	}
	long tick_after_us = argc == 5 ? atol(argv[4]) : -1;
	long rate_hz = atol(argv[1]);
	double seconds = atof(argv[2]);
	long busy_us = atol(argv[3]);
	if (rate_hz <= 0 || seconds <= 0 || seconds > 600 || busy_us < 0 ||
	    busy_us * rate_hz >= 1000000 || (argc == 5 && (tick_after_us < 0 || tick_after_us * rate_hz >= 1000000))) {
		fprintf(stderr, "RATE_HZ and SECONDS (at most 600) must be positive, BUSY_US "
				"and TICK_AFTER_US at least 0 and shorter than a period\n");
		return 2;
	}
	long samples = (long)(seconds * rate_hz);
	int64_t *woke = calloc(samples, sizeof *woke), *done = calloc(samples, sizeof *done);
	if (!woke || !done) {
		fprintf(stderr, "out of memory\n");
		return 1;
	}
	if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
		perror("mlockall");
	/* Held until the process exits; the kernel drops it then. */
	if (hold_latency_request() != 0)
		perror("/dev/cpu_dma_latency");
	if (on_cpu_fifo(1, 70) != 0)
		fprintf(stderr, "not on CPU 1 at SCHED_FIFO 70: the figures are a normal task's\n");
	int64_t ts = 1000000000LL / rate_hz, t0 = now_ns() + 2000000;
	if (tick_after_us >= 0)
		t0 = (t0 / 1000000 + 1) * 1000000 - tick_after_us * 1000;
	for (long k = 0; k < samples; k++) {
		int64_t tk = t0 + k * ts;
		struct timespec d = { tk / 1000000000LL, tk % 1000000000LL };
		clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &d, NULL);
		int64_t w = now_ns(), t = w;
		while (t - w < busy_us * 1000)
			t = now_ns();
		woke[k] = w - tk;
		done[k] = t - tk;
	}
	printf("k,woke_us,done_us\n");
	for (long k = 0; k < samples; k++)
		printf("%ld,%.3f,%.3f\n", k, woke[k] / 1e3, done[k] / 1e3);
	return 0;
}
