/*
 * How cold a task's memory is when it wakes: a SCHED_FIFO 70 timer on CPU 1 (memory locked,
 * CPU wake-up latency request of 0 held) wakes every 100 us and reads one byte on each of
 * LINES pages of a 4 MiB buffer (a 64-byte line per page, 4160 bytes apart), timing the
 * read, then reads them again at once (warm). With MODE "other" the timer wakes a second
 * process on the same CPU through a futex, and that process does the reads, as a stage
 * woken by the one before it; with "same" the timer's own process does them after its
 * sleep, with no switch to another process. HUGE 1 backs the buffer with transparent huge
 * pages (one TLB entry for all lines): if the cold read costs the same, the cost is in the
 * data caches, not the TLB. Prints the medians of 5 000 wake-ups.
 * docs/measurements.md, "The same VM three hours later".
 *
 *   gcc -O2 -o cold_after_sleep cold_after_sleep.c
 *   ./cold_after_sleep 64 same 0;  ./cold_after_sleep 64 other 0
 */
#define _GNU_SOURCE
#include <fcntl.h>
#include <linux/futex.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#define WAKEUPS 5000
#define PERIOD_NS 100000ull
#define STRIDE 4160
#define BUF (4ul << 20)

static uint64_t now(void)
{
	struct timespec t;
	clock_gettime(CLOCK_MONOTONIC, &t);
	return (uint64_t)t.tv_sec * 1000000000ull + (uint64_t)t.tv_nsec;
}

static int cmp(const void *a, const void *b)
{
	uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
	return x < y ? -1 : x > y;
}

/* Reads the lines twice; stores the cold and the warm time of wake-up i. */
static void touch(const volatile char *buf, int lines, uint64_t *res, int i)
{
	uint64_t a = now();
	for (int j = 0; j < lines; j++)
		(void)buf[(size_t)j * STRIDE];
	uint64_t b = now();
	for (int j = 0; j < lines; j++)
		(void)buf[(size_t)j * STRIDE];
	uint64_t c = now();
	res[2 * i] = b - a;
	res[2 * i + 1] = c - b;
}

int main(int argc, char **argv)
{
	if (argc != 4 || (strcmp(argv[2], "same") && strcmp(argv[2], "other"))) {
		fprintf(stderr, "usage: %s LINES same|other HUGE(0|1)\n", argv[0]);
		return 2;
	}
	int lines = atoi(argv[1]), other = !strcmp(argv[2], "other"), huge = atoi(argv[3]);
	if (lines < 1 || (size_t)lines * STRIDE >= BUF) {
		fprintf(stderr, "LINES must be 1..%lu\n", BUF / STRIDE);
		return 2;
	}
	cpu_set_t c;
	CPU_ZERO(&c);
	CPU_SET(1, &c);
	struct sched_param sp = { .sched_priority = 70 };
	if (sched_setaffinity(0, sizeof c, &c) || sched_setscheduler(0, SCHED_FIFO, &sp) ||
	    mlockall(MCL_CURRENT | MCL_FUTURE)) {
		perror("CPU 1, SCHED_FIFO 70, mlockall (run as root)");
		return 1;
	}
	int qos = open("/dev/cpu_dma_latency", O_WRONLY);
	int32_t zero = 0;
	if (qos < 0 || write(qos, &zero, 4) != 4)
		perror("/dev/cpu_dma_latency (measuring without the request)");
	_Atomic uint32_t *word = mmap(0, 4096, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
	uint64_t *res = mmap(0, WAKEUPS * 16, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
	char *raw = mmap(0, 2 * BUF, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
	if (word == MAP_FAILED || res == MAP_FAILED || raw == MAP_FAILED) {
		perror("mmap");
		return 1;
	}
	char *buf = (char *)(((uintptr_t)raw + (2u << 20) - 1) & ~(uintptr_t)((2u << 20) - 1));
	madvise(buf, BUF, huge ? MADV_HUGEPAGE : MADV_NOHUGEPAGE);
	memset(buf, 1, BUF);
	pid_t child = 0;
	if (other) {
		child = fork();
		if (child < 0) {
			perror("fork");
			return 1;
		}
	}
	if (child == 0 && other) {
		/* The woken process: the word counts the timer's wake-ups. */
		uint32_t seen = 0;
		while (seen < WAKEUPS) {
			while (atomic_load(word) == seen)
				syscall(SYS_futex, word, FUTEX_WAIT, seen, 0, 0, 0);
			seen = atomic_load(word);
			touch(buf, lines, res, (int)seen - 1);
		}
		_exit(0);
	}
	uint64_t t = now() + 1000000;
	for (int i = 0; i < WAKEUPS; i++) {
		t += PERIOD_NS;
		struct timespec ts = { (time_t)(t / 1000000000ull), (long)(t % 1000000000ull) };
		clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, 0);
		if (other) {
			atomic_fetch_add(word, 1);
			syscall(SYS_futex, word, FUTEX_WAKE, 1, 0, 0, 0);
		} else {
			touch(buf, lines, res, i);
		}
	}
	if (other)
		waitpid(child, 0, 0);
	/* A wake-up the woken process slept through (two timer wake-ups before it ran) left
	 * its entry at zero: only the measured ones count. */
	static uint64_t cold[WAKEUPS], warm[WAKEUPS];
	int n = 0;
	for (int i = 0; i < WAKEUPS; i++) {
		if (res[2 * i] == 0)
			continue;
		cold[n] = res[2 * i];
		warm[n] = res[2 * i + 1];
		n++;
	}
	if (n == 0) {
		fprintf(stderr, "no wake-up was measured\n");
		return 1;
	}
	qsort(cold, (size_t)n, 8, cmp);
	qsort(warm, (size_t)n, 8, cmp);
	uint64_t c50 = cold[n / 2], w50 = warm[n / 2];
	printf("%d lines, %s process, %s pages, %d wake-ups: after the sleep %lu ns, warm %lu ns "
	       "(p50), %.1f ns more per line\n",
	       lines, other ? "other" : "same", huge ? "huge" : "4 KiB", n, (unsigned long)c50,
	       (unsigned long)w50, ((double)c50 - (double)w50) / lines);
	return 0;
}
