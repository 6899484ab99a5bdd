/*
 * What the address spaces that ran in a sample cost the next timer wake-up. A timer task
 * (SCHED_FIFO 70, CPU 1, memory locked, CPU wake-up latency request held at 0) sleeps to
 * absolute deadlines and, per sample, wakes a chain of receivers through futex words, as the
 * plant wakes the stages after it. Each receiver (SCHED_FIFO 70 + 2i, CPU 1) lives in an
 * address space of its own choosing: a thread of the timer's process or of one of several
 * child processes. Which receivers a sample wakes changes every BLOCK samples, cycling through
 * the PHASEs given, so every phase sees the same host: on a VM whose timer switches between a
 * fast and a slow speed every few seconds, runs one after the other compare the speeds, not
 * the phases. docs/measurements.md, "A third address space in the sample".
 *
 *   gcc -O2 -o address_spaces address_spaces.c -lpthread
 *   ./address_spaces RATE_HZ SECONDS BLOCK GROUPS PHASE...
 *       GROUPS  comma list, receiver i's address space: 0 a thread of the timer's process,
 *               g > 0 a thread of child process g (so "1,2" two processes, "1,1" two threads
 *               of one process, "1,0" a process and a thread of the timer's own)
 *       PHASE   the receivers a sample wakes, in chain order ("12": 1 wakes 2), "-" none;
 *               with a "c" the timer task executes CPUID (a VM exit on a VM) before it
 *               sleeps, with a "w" it first sleeps 2 µs (a trip through the timer's own
 *               path); "a/b" alternates a and b sample by sample; up to 8 phases
 *       PAGES=N in the environment: every task writes one byte on each of N private pages
 *               per sample (a working set)
 *
 * Prints, per phase: the timer's lateness p50 / p99 over the run, and the median over the
 * cycles of phases of (this phase's block p50 − the first phase's block p50 of the same
 * cycle), over all cycles and over the cycles where the first phase's block p50 lies within
 * 2 µs of its fastest block (the timer's fast speed, as the bench picks its fastest slots).
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/wait.h>

#include "rt_helpers.h"

#define BUCKETS 100000 /* 0.1 µs each: 0 .. 10 ms */
#define MAXR 8
#define MAXP 8

struct shared {
	uint32_t words[(MAXR + 1) * STRIDE];
	uint64_t late[MAXP][BUCKETS];
	volatile int succ[MAXR + 1];
	volatile int stop;
};

static struct shared *s;
static int pages;

/* The task's working set: one byte on each of `pages` private pages. */
static void touch(void)
{
	static char *own;
	if (pages == 0)
		return;
	if (own == NULL && (own = calloc((size_t)pages, 4096)) == NULL)
		return;
	for (int j = 0; j < pages; j++)
		own[(size_t)j * 4096] += 1;
}

static void *receiver(void *arg)
{
	long i = (long)arg;
	on_cpu_fifo(1, 70 + 2 * (int)i);
	for (;;) {
		wait_token(&s->words[i * STRIDE]);
		if (s->stop)
			break;
		int next = s->succ[i];
		if (next > 0)
			pass_token(&s->words[next * STRIDE]);
		touch();
	}
	return NULL;
}

static void vm_exit(void)
{
#if defined(__x86_64__)
	unsigned a = 0, b, c = 0, d;
	__asm__ volatile("cpuid" : "+a"(a), "=b"(b), "+c"(c), "=d"(d));
#endif
}

static int cmp_i32(const void *x, const void *y)
{
	int32_t a = *(const int32_t *)x, b = *(const int32_t *)y;
	return (a > b) - (a < b);
}

static int cmp_double(const void *x, const void *y)
{
	double a = *(const double *)x, b = *(const double *)y;
	return (a > b) - (a < b);
}

static double median(double *v, int n)
{
	qsort(v, (size_t)n, sizeof *v, cmp_double);
	return n == 0 ? 0.0 : (n % 2 ? v[n / 2] : (v[n / 2 - 1] + v[n / 2]) / 2);
}

int main(int argc, char **argv)
{
	if (argc < 6) {
		fprintf(stderr, "usage: %s RATE_HZ SECONDS BLOCK GROUPS PHASE...\n", argv[0]);
		return 2;
	}
	long rate = atol(argv[1]), samples = rate * atol(argv[2]), block = atol(argv[3]);
	int group[MAXR + 1] = { 0 }, k = 0, np = argc - 5;
	char **phase = argv + 5;
	for (char *t = strtok(argv[4], ","); t && k < MAXR; t = strtok(NULL, ","))
		group[++k] = atoi(t);
	if (rate <= 0 || samples <= 0 || block <= 0 || np > MAXP) {
		fprintf(stderr, "RATE_HZ, SECONDS and BLOCK positive, at most %d phases\n", MAXP);
		return 2;
	}
	pages = getenv("PAGES") ? atoi(getenv("PAGES")) : 0;
	if (hold_latency_request() != 0)
		perror("/dev/cpu_dma_latency");
	s = mmap(NULL, sizeof *s, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
	int32_t *raw = mmap(NULL, (size_t)samples * 4, PROT_READ | PROT_WRITE,
			    MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
	if (s == MAP_FAILED || raw == MAP_FAILED) {
		perror("mmap");
		return 1;
	}
	if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
		perror("mlockall");
	int groups = 0;
	for (int i = 1; i <= k; i++)
		groups = group[i] > groups ? group[i] : groups;
	pid_t pid[MAXR + 1];
	for (int g = 1; g <= groups; g++) {
		if ((pid[g] = fork()) == 0) {
			pthread_t t[MAXR];
			int n = 0;
			for (long i = 1; i <= k; i++)
				if (group[i] == g)
					pthread_create(&t[n++], NULL, receiver, (void *)i);
			for (int j = 0; j < n; j++)
				pthread_join(t[j], NULL);
			_exit(0);
		}
	}
	pthread_t own[MAXR + 1];
	for (long i = 1; i <= k; i++)
		if (group[i] == 0)
			pthread_create(&own[i], NULL, receiver, (void *)i);
	on_cpu_fifo(1, 70);
	usleep(200000);
	int64_t period = 1000000000LL / rate, t0 = now_ns() + period;
	for (long n = 0; n < samples; n++) {
		int p = (int)((n / block) % np);
		if (strchr(phase[p], 'c'))
			vm_exit();
		if (strchr(phase[p], 'w')) {
			int64_t w = now_ns() + 2000;
			struct timespec ws = { w / 1000000000LL, w % 1000000000LL };
			clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ws, NULL);
		}
		int64_t tk = t0 + n * period;
		struct timespec d = { tk / 1000000000LL, tk % 1000000000LL };
		clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &d, NULL);
		int64_t late = now_ns() - tk;
		/* A block's first wake-up follows the previous phase's chain: counted in neither
		 * (the block p50s below start at its second sample). */
		if (n % block != 0)
			hist_record(s->late[p], BUCKETS, 100, late);
		raw[n] = (int32_t)late;
		const char *c = phase[p], *slash = strchr(c, '/');
		if (slash && (n & 1))
			c = slash + 1;
		int first = 0, prev = 0;
		for (; *c && *c != '/'; c++) {
			if (*c < '1' || *c > '0' + k)
				continue;
			int r = *c - '0';
			if (prev)
				s->succ[prev] = r;
			else
				first = r;
			prev = r;
		}
		if (prev)
			s->succ[prev] = 0;
		if (first)
			pass_token(&s->words[first * STRIDE]);
		touch();
	}
	s->stop = 1;
	for (int i = 1; i <= k; i++)
		pass_token(&s->words[i * STRIDE]);
	for (int g = 1; g <= groups; g++)
		waitpid(pid[g], NULL, 0);

	/* Block p50s, µs, per cycle of phases. */
	long cycles = samples / (block * np);
	double *bp = calloc((size_t)(cycles * np), sizeof *bp), *diff = calloc((size_t)cycles, sizeof *diff);
	int32_t *tmp = calloc((size_t)block, sizeof *tmp);
	double fastest = 1e9;
	for (long cy = 0; cy < cycles; cy++) {
		for (int p = 0; p < np; p++) {
			long from = (cy * np + p) * block + 1;
			memcpy(tmp, raw + from, (size_t)(block - 1) * sizeof *tmp);
			qsort(tmp, (size_t)(block - 1), sizeof *tmp, cmp_i32);
			bp[cy * np + p] = tmp[(block - 1) / 2] / 1000.0;
		}
		fastest = bp[cy * np] < fastest ? bp[cy * np] : fastest;
	}
	printf("phase     late p50   p99 | − phase %s, median over cycles: all (%ld)  fast\n",
	       phase[0], cycles);
	for (int p = 0; p < np; p++) {
		int m = 0, f = 0;
		for (long cy = 0; cy < cycles; cy++)
			diff[m++] = bp[cy * np + p] - bp[cy * np];
		double all = median(diff, m);
		for (long cy = 0; cy < cycles; cy++)
			if (bp[cy * np] <= fastest + 2.0)
				diff[f++] = bp[cy * np + p] - bp[cy * np];
		double fast = median(diff, f);
		printf("%-8s %9.1f %5.1f | %+38.2f %+6.2f (%d cycles)\n", phase[p],
		       hist_percentile_us(s->late[p], BUCKETS, 100, .5),
		       hist_percentile_us(s->late[p], BUCKETS, 100, .99), all, fast, f);
	}
	return 0;
}
