/*
 * A lone SCHED_FIFO 70 timer thread on CPU 1 (absolute clock_nanosleep, memory locked, no
 * CPU wake-up latency request), with or without a companion: the main thread, also on
 * CPU 1, waking every COMPANION_MS ms at SCHED_OTHER (cyclictest -a 1's layout with 10 ms).
 * Prints the timer thread's wake-up lateness p50 and p99. docs/measurements.md, "What
 * cyclictest does differently: its main thread".
 *
 *   gcc -O2 -o timer_companion timer_companion.c -lpthread
 *   ./timer_companion RATE_HZ SECONDS COMPANION_MS     (COMPANION_MS 0: the main thread blocks)
 */
#define _GNU_SOURCE
#include <pthread.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <time.h>

#include "rt_helpers.h"

#define BUCKETS 100000 /* 0.1 µs each: 0 .. 10 ms */

static uint64_t hist[BUCKETS];
static long rate_hz, samples;
static volatile int done;

static void *timer_thread(void *unused)
{
	(void)unused;
	on_cpu_fifo(1, 70);
	int64_t ts = 1000000000LL / rate_hz, t0 = now_ns() + ts;
	for (long k = 0; k < samples; k++) {
		int64_t tk = t0 + k * ts;
		struct timespec d = { tk / 1000000000LL, tk % 1000000000LL };
		clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &d, NULL);
		hist_record(hist, BUCKETS, 100, now_ns() - tk);
	}
	done = 1;
	return NULL;
}

int main(int argc, char **argv)
{
	if (argc != 4) {
		fprintf(stderr, "usage: %s RATE_HZ SECONDS COMPANION_MS\n", argv[0]);
		return 2;
	}
	rate_hz = atol(argv[1]);
	samples = (long)(atof(argv[2]) * rate_hz);
	long companion_ms = atol(argv[3]);
	if (rate_hz <= 0 || samples <= 0 || companion_ms < 0) {
		fprintf(stderr, "RATE_HZ and SECONDS must be positive, COMPANION_MS >= 0\n");
		return 2;
	}
	if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
		perror("mlockall");
	pthread_t t;
	pthread_create(&t, NULL, timer_thread, NULL);
	pin_to(1);
	while (companion_ms > 0 && !done) {
		struct timespec d = { companion_ms / 1000, (companion_ms % 1000) * 1000000L };
		clock_nanosleep(CLOCK_REALTIME, 0, &d, NULL);
	}
	pthread_join(t, NULL);
	printf("companion %ld ms: p50 %.1f us, p99 %.1f us\n", companion_ms,
	       hist_percentile_us(hist, BUCKETS, 100, .5), hist_percentile_us(hist, BUCKETS, 100, .99));
	return 0;
}
