/*
 * N tasks on CPU 1 at SCHED_FIFO 70 pass a token round a ring: each waits on its own futex
 * word in shared memory, then wakes the next. Run as N processes or as N threads of one
 * process, it prints the time per hop (one futex wake, one switch), so the cost of changing
 * address spaces is the difference. docs/measurements.md, "A hop is a wake-up and a switch".
 *
 *   gcc -O2 -o futex_ring futex_ring.c -lpthread
 *   ./futex_ring N THREADS ROUNDS     (N 2..16; THREADS 0: processes, 1: threads)
 */
#define _GNU_SOURCE
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

static int n_tasks;
static long rounds;
static uint32_t *words;

static uint32_t *word(long i)
{
	return &words[(i % n_tasks) * STRIDE];
}

static void *task(void *arg)
{
	long i = (long)arg;
	on_cpu_fifo(1, 70);
	for (long r = 0; r < rounds; r++) {
		wait_token(word(i));
		pass_token(word(i + 1));
	}
	return NULL;
}

int main(int argc, char **argv)
{
	if (argc != 4) {
		fprintf(stderr, "usage: %s N THREADS ROUNDS\n", argv[0]);
		return 2;
	}
	n_tasks = atoi(argv[1]);
	int threads = atoi(argv[2]);
	rounds = atol(argv[3]);
	if (n_tasks < 2 || n_tasks > 16 || rounds <= 0) {
		fprintf(stderr, "N must be in 2..16 and ROUNDS positive\n");
		return 2;
	}
	if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
		perror("mlockall");
	words = mmap(NULL, 4096, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
	if (words == MAP_FAILED) {
		perror("mmap");
		return 1;
	}
	pthread_t th[16];
	pid_t pid[16];
	for (long i = 1; i < n_tasks; i++) {
		if (threads) {
			pthread_create(&th[i], NULL, task, (void *)i);
		} else if ((pid[i] = fork()) == 0) {
			task((void *)i);
			_exit(0);
		}
	}
	on_cpu_fifo(1, 70);
	usleep(100000);
	int64_t t0 = now_ns();
	for (long r = 0; r < rounds; r++) {
		pass_token(word(1));
		wait_token(word(0));
	}
	int64_t t1 = now_ns();
	for (long i = 1; i < n_tasks; i++) {
		if (threads)
			pthread_join(th[i], NULL);
		else
			waitpid(pid[i], NULL, 0);
	}
	printf("%d %s: %.2f us per hop\n", n_tasks, threads ? "threads" : "processes",
	       (t1 - t0) / 1e3 / rounds / n_tasks);
	return 0;
}
