/*
 * A timer task and a chain of K receivers on CPU 1, as the default drive's critical path
 * without drivelab: the timer task (SCHED_FIFO 70) sleeps to absolute deadlines, records its
 * lateness and wakes receiver 1 through a futex word; receiver i (SCHED_FIFO 70 + 2i) wakes
 * receiver i + 1; the last records deadline → running (the cycle). Optionally every task
 * spins WORK_NS after it wakes (the timer task after it woke receiver 1, where the plant
 * integrates), to give the chain the drive's CPU time per sample. The CPU wake-up latency
 * request is held at 0. Prints lateness and cycle p50 / p99 / p99.9, µs (100 ns buckets).
 * docs/measurements.md, "The bare chain".
 *
 *   gcc -O2 -o timer_chain timer_chain.c -lpthread
 *   ./timer_chain RATE_HZ SECONDS K THREADS [WORK_NS]
 *       (K 0..16 receivers; THREADS 0: processes, 1: threads of this process)
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <linux/futex.h>
#include <pthread.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "rt_helpers.h"

#define BUCKETS 100000 /* 0.1 µs each: 0 .. 10 ms */

struct shared {
	uint32_t words[17 * STRIDE];
	uint64_t late[BUCKETS];
	uint64_t cycle[BUCKETS];
	volatile int64_t deadline;
	volatile int stop;
};

static struct shared *s;
static int k_receivers;
static long work_ns;

static void record(uint64_t *h, int64_t ns)
{
	hist_record(h, BUCKETS, 100, ns);
}

static void spin(void)
{
	if (work_ns == 0)
		return;
	int64_t end = now_ns() + work_ns;
	while (now_ns() < end)
		;
}

static void *receiver(void *arg)
{
	long i = (long)arg;
	on_cpu_fifo(1, 70 + 2 * i);
	for (;;) {
		wait_token(&s->words[i * STRIDE]);
		if (s->stop)
			break;
		spin();
		if (i < k_receivers)
			pass_token(&s->words[(i + 1) * STRIDE]);
		else /* behind by more than a period this reads a newer deadline: not used then */
			record(s->cycle, now_ns() - s->deadline);
	}
	return NULL;
}

static double percentile(const uint64_t *h, double q)
{
	return hist_percentile_us(h, BUCKETS, 100, q);
}

int main(int argc, char **argv)
{
	if (argc < 5) {
		fprintf(stderr, "usage: %s RATE_HZ SECONDS K THREADS [WORK_NS]\n", argv[0]);
		return 2;
	}
	long rate = atol(argv[1]), samples = rate * atol(argv[2]);
	k_receivers = atoi(argv[3]);
	int threads = atoi(argv[4]);
	work_ns = argc > 5 ? atol(argv[5]) : 0;
	if (rate <= 0 || samples <= 0 || k_receivers < 0 || k_receivers > 16 || work_ns < 0) {
		fprintf(stderr, "RATE_HZ and SECONDS positive, K in 0..16, WORK_NS >= 0\n");
		return 2;
	}
	if (hold_latency_request() != 0)
		perror("/dev/cpu_dma_latency");
	s = mmap(NULL, sizeof *s, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
	if (s == MAP_FAILED) {
		perror("mmap");
		return 1;
	}
	if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
		perror("mlockall");
	pthread_t th[17];
	pid_t pid[17];
	for (long i = 1; i <= k_receivers; i++) {
		if (threads) {
			pthread_create(&th[i], NULL, receiver, (void *)i);
		} else if ((pid[i] = fork()) == 0) {
			receiver((void *)i);
			_exit(0);
		}
	}
	on_cpu_fifo(1, 70);
	usleep(100000);
	int64_t period = 1000000000LL / rate, t0 = now_ns() + period;
	for (long k = 0; k < samples; k++) {
		int64_t tk = t0 + k * period;
		struct timespec d = { tk / 1000000000LL, tk % 1000000000LL };
		clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &d, NULL);
		int64_t late = now_ns() - tk;
		record(s->late, late);
		s->deadline = tk;
		if (k_receivers > 0)
			pass_token(&s->words[STRIDE]);
		else
			record(s->cycle, late);
		spin();
	}
	s->stop = 1;
	for (long i = 1; i <= k_receivers; i++)
		pass_token(&s->words[i * STRIDE]);
	for (long i = 1; i <= k_receivers; i++) {
		if (threads)
			pthread_join(th[i], NULL);
		else
			waitpid(pid[i], NULL, 0);
	}
	printf("W=%ld K=%d %s late p50 %.1f p99 %.1f p999 %.1f cyc p50 %.1f p99 %.1f p999 %.1f\n",
	       work_ns, k_receivers, threads ? "threads" : "processes", percentile(s->late, .5),
	       percentile(s->late, .99), percentile(s->late, .999), percentile(s->cycle, .5),
	       percentile(s->cycle, .99), percentile(s->cycle, .999));
	return 0;
}
