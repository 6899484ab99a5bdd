/*
 * What the C reproductions in this folder share: the monotonic clock, the CPU wake-up latency
 * request, a task on one CPU at SCHED_FIFO, a futex token passed from task to task, and a histogram of fixed-width
 * buckets with its percentiles. Header-only (every function static), so each program still
 * builds with one `gcc` line.
 */
#ifndef DRIVELAB_BENCH_RT_HELPERS_H
#define DRIVELAB_BENCH_RT_HELPERS_H

#include <fcntl.h>
#include <linux/futex.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

/* One 64-byte line per futex word, so that two tasks' words never share a line. */
#define STRIDE 16

static inline int64_t now_ns(void)
{
	struct timespec t;
	clock_gettime(CLOCK_MONOTONIC, &t);
	return t.tv_sec * 1000000000LL + t.tv_nsec;
}

/* Holds a CPU wake-up latency request of 0 µs (as cyclictest does) until the process exits,
 * when the kernel drops it. Returns 0, or -1 with errno set when it cannot be made. */
static inline int hold_latency_request(void)
{
	int32_t zero = 0;
	int fd = open("/dev/cpu_dma_latency", O_WRONLY);
	return fd >= 0 && write(fd, &zero, sizeof zero) == sizeof zero ? 0 : -1;
}

/* Pins the calling task to `cpu`. */
static inline void pin_to(int cpu)
{
	cpu_set_t c;
	CPU_ZERO(&c);
	CPU_SET(cpu, &c);
	if (sched_setaffinity(0, sizeof c, &c) != 0)
		perror("sched_setaffinity");
}

/* Pins the calling task to `cpu` and runs it at SCHED_FIFO `prio`; where that is refused
 * it says so and returns -1 (the measurements go on without it), else 0. */
static inline int on_cpu_fifo(int cpu, int prio)
{
	pin_to(cpu);
	struct sched_param p = { .sched_priority = prio };
	if (sched_setscheduler(0, SCHED_FIFO, &p) != 0) {
		perror("sched_setscheduler (SCHED_FIFO needs root or CAP_SYS_NICE)");
		return -1;
	}
	return 0;
}

/* Sleeps on the futex word until another task has passed the token, then takes it. */
static inline void wait_token(uint32_t *w)
{
	while (__atomic_load_n(w, __ATOMIC_ACQUIRE) == 0)
		syscall(SYS_futex, w, FUTEX_WAIT, 0, NULL, NULL, 0);
	__atomic_store_n(w, 0, __ATOMIC_RELEASE);
}

/* Passes the token and wakes the task that waits on the word. */
static inline void pass_token(uint32_t *w)
{
	__atomic_store_n(w, 1, __ATOMIC_RELEASE);
	syscall(SYS_futex, w, FUTEX_WAKE, 1, NULL, NULL, 0);
}

/* Counts `ns` in a histogram of `buckets` buckets of `bucket_ns` each; below 0 in the first,
 * beyond the last in the last. */
static inline void hist_record(uint64_t *h, int buckets, int64_t bucket_ns, int64_t ns)
{
	int64_t b = ns < 0 ? 0 : ns / bucket_ns;
	h[b < buckets ? b : buckets - 1]++;
}

/* The q-quantile (0..1) of such a histogram, µs (its bucket's lower edge); -1 when empty. */
static inline double hist_percentile_us(const uint64_t *h, int buckets, int64_t bucket_ns,
					double q)
{
	uint64_t n = 0, c = 0;
	for (int b = 0; b < buckets; b++)
		n += h[b];
	if (n == 0)
		return -1;
	for (int b = 0; b < buckets; b++) {
		c += h[b];
		if (c >= q * n)
			return b * bucket_ns / 1000.0;
	}
	return -1;
}

#endif
