/*
 * What a switch between processes costs the code that runs after it, page by page.
 *
 * A timer task (SCHED_FIFO 70, CPU 1) sleeps to absolute deadlines and wakes a receiver
 * (SCHED_FIFO 72, CPU 1) through a futex word, as the plant wakes the observer. The receiver,
 * once running, reads one cache line on each of PAGES pages of its own memory and records how
 * long that took (first pass), then reads them again (second pass: the same lines, now in the
 * TLB and the cache). The receiver is either a second process (every switch to it loads
 * another address space) or a second thread of the timer's process (no address-space switch).
 * Its pages are either 4 KiB pages or lie in one 2 MiB transparent huge page (madvise).
 *
 * On a CPU without PCID (or ASIDs) every address-space switch flushes the TLB's user entries,
 * so the first pass after a process switch pays one page walk per page; with nested paging a
 * walk costs far more than on bare metal. The first pass minus the second, processes against
 * threads, is that cost. The CPU wake-up latency request is held at 0.
 * docs/measurements.md, "The TLB after a switch".
 *
 *   gcc -O2 -o tlb_after_switch tlb_after_switch.c -lpthread
 *   ./tlb_after_switch RATE_HZ SECONDS PAGES THREADS HUGE [CODE]
 *       (PAGES 0..512; THREADS 0: processes, 1: threads; HUGE 0: 4 KiB pages, 1: one 2 MiB page;
 *        CODE 1: instead of reading data, call PAGES (at most 64) functions, one per code page)
 * Prints the receiver's first and second pass, p50 / p99, ns (10 ns buckets), the timer task's
 * pass over its own pages right after its wake-up (it touched them before it slept), and
 * whether the huge page was granted (AnonHugePages of the receiver's mapping).
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <linux/futex.h>
#include <pthread.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "rt_helpers.h"

#define BUCKETS 100000 /* 10 ns each: 0 .. 1 ms */
#define HUGE (2UL << 20)

struct shared {
	uint32_t word;
	char pad[60];
	uint64_t first[BUCKETS];
	uint64_t second[BUCKETS];
	uint64_t timer_first[BUCKETS];
	volatile int stop;
	volatile long huge_kb;
};

static struct shared *s;
static int pages;
static int huge;
static int code;

/* 64 functions, each on a code page of its own */
#define FN(i) \
	__attribute__((noinline, aligned(4096))) static uint64_t f##i(uint64_t x) \
	{ \
		__asm__ volatile("" : "+r"(x)); \
		return x * 3 + i; \
	}
#define FN8(a) FN(a##0) FN(a##1) FN(a##2) FN(a##3) FN(a##4) FN(a##5) FN(a##6) FN(a##7)
FN8(1) FN8(2) FN8(3) FN8(4) FN8(5) FN8(6) FN8(7) FN8(8)
#define P8(a) f##a##0, f##a##1, f##a##2, f##a##3, f##a##4, f##a##5, f##a##6, f##a##7
static uint64_t (*const fns[64])(uint64_t) = { P8(1), P8(2), P8(3), P8(4), P8(5), P8(6), P8(7), P8(8) };

static void record(uint64_t *h, int64_t ns)
{
	hist_record(h, BUCKETS, 10, ns);
}

/* ns */
static double pct(const uint64_t *h, double q)
{
	return hist_percentile_us(h, BUCKETS, 10, q) * 1000.0;
}

/* The receiver's memory: PAGES pages, one line read on each, at offsets that spread the
 * lines over the cache's sets. 4 KiB mode: its own mapping, huge pages refused. Huge mode:
 * the lines lie 4 KiB apart inside one 2 MiB-aligned huge page. */
static volatile uint64_t *region(void)
{
	size_t len = 2 * HUGE;
	char *m = mmap(NULL, len, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
	if (m == MAP_FAILED) {
		perror("mmap");
		exit(1);
	}
	char *a = (char *)(((uintptr_t)m + HUGE - 1) & ~(HUGE - 1));
	madvise(a, HUGE, huge ? MADV_HUGEPAGE : MADV_NOHUGEPAGE);
	memset(a, 1, HUGE);
	mlock(a, HUGE);
	/* AnonHugePages of this mapping, from smaps */
	FILE *f = fopen("/proc/self/smaps", "r");
	char line[256];
	int in = 0;
	long kb = 0;
	while (f && fgets(line, sizeof line, f)) {
		unsigned long lo, hi;
		if (sscanf(line, "%lx-%lx", &lo, &hi) == 2 && strchr(line, ' ') - line < 40)
			in = lo <= (uintptr_t)a && (uintptr_t)a < hi;
		else if (in && sscanf(line, "AnonHugePages: %ld kB", &kb) == 1)
			s->huge_kb = kb;
	}
	if (f)
		fclose(f);
	return (volatile uint64_t *)a;
}

static uint64_t pass(volatile uint64_t *a)
{
	uint64_t sum = 0;
	if (code) {
		for (int i = 0; i < pages && i < 64; i++)
			sum = fns[i](sum);
		return sum;
	}
	for (int i = 0; i < pages; i++)
		sum += a[(i * 4096 + (i % 64) * 64) / 8];
	return sum;
}

static void *receiver(void *arg)
{
	(void)arg;
	on_cpu_fifo(1, 72);
	volatile uint64_t *a = region();
	uint64_t sink = 0;
	for (;;) {
		while (__atomic_load_n(&s->word, __ATOMIC_ACQUIRE) == 0) {
			if (s->stop)
				goto out;
			syscall(SYS_futex, &s->word, FUTEX_WAIT, 0, NULL, NULL, 0);
		}
		__atomic_store_n(&s->word, 0, __ATOMIC_RELAXED);
		int64_t t0 = now_ns();
		sink += pass(a);
		int64_t t1 = now_ns();
		sink += pass(a);
		int64_t t2 = now_ns();
		record(s->first, t1 - t0);
		record(s->second, t2 - t1);
	}
out:
	return (void *)(uintptr_t)sink;
}

int main(int argc, char **argv)
{
	if (argc != 6 && argc != 7) {
		fprintf(stderr, "usage: %s RATE_HZ SECONDS PAGES THREADS HUGE [CODE]\n", argv[0]);
		return 2;
	}
	long rate = atol(argv[1]);
	double seconds = atof(argv[2]);
	pages = atoi(argv[3]);
	int threads = atoi(argv[4]);
	huge = atoi(argv[5]);
	code = argc == 7 && atoi(argv[6]);
	if (rate < 100 || rate > 50000 || pages < 0 || pages > 512 || seconds <= 0) {
		fprintf(stderr, "out of range\n");
		return 2;
	}
	s = mmap(NULL, sizeof *s, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
	if (s == MAP_FAILED) {
		perror("mmap");
		return 1;
	}
	memset(s, 0, sizeof *s);
	s->huge_kb = -1;
	mlockall(MCL_CURRENT | MCL_FUTURE);
	if (hold_latency_request() != 0)
		fprintf(stderr, "no CPU latency request\n");

	pid_t child = -1;
	pthread_t th;
	if (threads) {
		pthread_create(&th, NULL, receiver, NULL);
	} else {
		child = fork();
		if (child == 0) {
			receiver(NULL);
			_exit(0);
		}
	}
	on_cpu_fifo(1, 70);
	usleep(200000);
	memset(s->first, 0, sizeof s->first);
	memset(s->second, 0, sizeof s->second);
	memset(s->timer_first, 0, sizeof s->timer_first);
	volatile uint64_t *mine = region();
	uint64_t sink = pass(mine);

	long period = 1000000000L / rate;
	long n = (long)(seconds * rate);
	struct timespec next;
	clock_gettime(CLOCK_MONOTONIC, &next);
	for (long k = 0; k < n; k++) {
		next.tv_nsec += period;
		if (next.tv_nsec >= 1000000000L) {
			next.tv_nsec -= 1000000000L;
			next.tv_sec++;
		}
		clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
		int64_t t0 = now_ns();
		sink += pass(mine);
		record(s->timer_first, now_ns() - t0);
		__atomic_store_n(&s->word, 1, __ATOMIC_RELEASE);
		syscall(SYS_futex, &s->word, FUTEX_WAKE, 1, NULL, NULL, 0);
		sink += pass(mine); /* after the receiver ran, as the plant integrates */
	}
	s->stop = 1;
	__atomic_store_n(&s->word, 0, __ATOMIC_RELEASE);
	syscall(SYS_futex, &s->word, FUTEX_WAKE, 1, NULL, NULL, 0);
	if (threads)
		pthread_join(th, NULL);
	else
		waitpid(child, NULL, 0);
	printf("%s %s %s pages=%d huge_kb=%ld receiver first p50 %.0f p99 %.0f ns, second p50 %.0f p99 %.0f ns; timer first p50 %.0f p99 %.0f ns (%lu)\n",
	       threads ? "threads  " : "processes", code ? "code" : "data", huge ? "2M" : "4K", pages, s->huge_kb,
	       pct(s->first, 0.5), pct(s->first, 0.99), pct(s->second, 0.5), pct(s->second, 0.99),
	       pct(s->timer_first, 0.5), pct(s->timer_first, 0.99), (unsigned long)(sink & 1));
	return 0;
}
