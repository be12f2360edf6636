/* The thread pool of the compiled kernels (issue 24; built and loaded by torchconn/ops/native.py,
 * which hands tc_pool_run to every kernel library through its tc_pool_attach, below).
 *
 * tc_pool_run(n, nt, fn, ctx) runs fn(ctx, 0) ... fn(ctx, n - 1), the tasks of one parallel
 * loop, on the calling thread and up to nt - 1 workers, and returns when all have run. Unlike
 * an OpenMP parallel region it never waits for a thread that has not started:
 *
 *   - tasks are claimed one at a time from a shared counter (work stealing), by the caller too:
 *     a worker that is not scheduled (its core taken by another process) claims nothing, and
 *     the caller runs the tasks it would have run;
 *   - the caller then waits only for the tasks already claimed by running workers, and it
 *     waits asleep (a condition variable after a short spin), so that the core it frees can
 *     take over a worker preempted by another process (idle balancing moves it there);
 *   - workers sleep on a condition variable between loops (after a short spin): an idle pool
 *     takes no CPU from torch's own threads or other processes.
 *
 * With OpenMP's fork-join every region ends in a barrier that waits for every thread of the
 * team, and GNU OpenMP threads spin there (by default up to ~300k iterations): on a 2-core
 * machine with one core held by another process, a training step of curvature + averaged d∇
 * took 10x the one-thread time (benchmarks/under_load.py).
 *
 * Which task runs on which thread is not fixed, so kernels keep their results independent of
 * the threads: every task writes its own outputs, and per-task partial sums are combined in
 * task order by the caller (the chunking of a loop never depends on nt).
 *
 * One loop at a time: a call while another thread's loop runs (two Python threads calling
 * kernels) runs its tasks serially on its own thread instead of waiting. A child process after
 * fork() starts with no workers (they are created again when needed).
 *
 * Exported: void tc_pool_run(long n, int nt, void (*fn)(void *, long), void *ctx)
 *           int tc_pool_workers(void): workers created so far (for the tests)
 * (a C file, not a header, so that it ships with the other kernel sources)
 */
#ifndef TC_POOL_C
#define TC_POOL_C

typedef void (*tc_task_fn)(void *ctx, long task);

#ifdef TC_POOL_CLIENT
/* The client side (a kernel file defines TC_POOL_CLIENT and includes this file): the parallel
 * loop of the kernel libraries, tc_parallel(n, nt, fn, ctx) runs fn(ctx, task)
 * for task = 0 .. n - 1 on up to nt threads (the caller included) through the pool of pool.c,
 * whose tc_pool_run torchconn/ops/native.py hands to every kernel library when it loads it
 * (tc_pool_attach, exported by each library that includes this file). Without a pool (not
 * attached, or nt <= 1) the tasks run in order on the calling thread.
 *
 * Tasks are claimed dynamically (see pool.c): a task must write only its own outputs, or its
 * own slot of a partial-result array that the caller combines in task order afterwards, so
 * that results never depend on which thread ran which task nor on nt (split loops into tasks
 * by sizes that do not depend on nt).
 */

typedef void (*tc_run_fn)(long n, int nt, tc_task_fn fn, void *ctx);

static tc_run_fn tc_pool_run_ptr;

/* set by native.py at load time: the address of pool.c's tc_pool_run */
void tc_pool_attach(void *run)
{
    __atomic_store_n(&tc_pool_run_ptr, (tc_run_fn)run, __ATOMIC_RELEASE);
}

static inline void tc_parallel(long n, int nt, tc_task_fn fn, void *ctx)
{
    tc_run_fn run = __atomic_load_n(&tc_pool_run_ptr, __ATOMIC_ACQUIRE);
    if (run && nt > 1 && n > 1) {
        run(n, nt, fn, ctx);
        return;
    }
    for (long i = 0; i < n; ++i)
        fn(ctx, i);
}

/* the number of tasks of `chunk` items each that cover n items */
static inline long tc_tasks(long n, long chunk)
{
    return n > 0 ? (n + chunk - 1) / chunk : 0;
}


#else /* ------------------------------------------------------------- the pool library */

#define _GNU_SOURCE
#include <pthread.h>
#include <signal.h>
#include <time.h>

#define TC_MAX_WORKERS 255
/* spins before sleeping: a worker waiting for the next loop, the caller waiting for claimed
 * tasks (nanoseconds); short, so that a waiting thread gives its core back quickly */
#define TC_SPIN_NS 20000L

static pthread_mutex_t tc_mu = PTHREAD_MUTEX_INITIALIZER;    /* workers, sleeping, epoch waits */
static pthread_cond_t tc_work = PTHREAD_COND_INITIALIZER;    /* a new loop was published */
static pthread_cond_t tc_done = PTHREAD_COND_INITIALIZER;    /* the last task of a loop ended */
static pthread_mutex_t tc_submit = PTHREAD_MUTEX_INITIALIZER; /* one loop at a time */

/* the current loop: fn, ctx, n and want are written before `state` is published (release) and
 * not changed until every task has run. state = (epoch << 32) | next unclaimed task */
static tc_task_fn tc_fn;
static void *tc_ctx;
static long tc_n;
static int tc_want;            /* workers 0 .. want - 1 take part (nt - 1) */
static long tc_state;
static long tc_finished;       /* tasks of the current loop that have run */
static int tc_nworkers;        /* created */
static int tc_sleeping;        /* waiting on tc_work */
static int tc_caller_sleeping; /* the caller waits on tc_done */

static long tc_now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long)ts.tv_sec * 1000000000L + ts.tv_nsec;
}

static inline void tc_relax(void)
{
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#endif
}

/* claim and run tasks of loop `epoch` until none is left (or another loop is published) */
static void tc_run_tasks(long epoch)
{
    for (;;) {
        long s = __atomic_load_n(&tc_state, __ATOMIC_ACQUIRE);
        if ((s >> 32) != epoch)
            return;
        long i = s & 0xffffffffL;
        if (i >= __atomic_load_n(&tc_n, __ATOMIC_RELAXED))
            return;
        /* the claim succeeds only if the loop is still `epoch` with task i unclaimed: then the
         * loop is unfinished, so fn and ctx read after the load above are still its own */
        tc_task_fn fn = __atomic_load_n(&tc_fn, __ATOMIC_RELAXED);
        void *ctx = __atomic_load_n(&tc_ctx, __ATOMIC_RELAXED);
        long n = __atomic_load_n(&tc_n, __ATOMIC_RELAXED);
        if (!__atomic_compare_exchange_n(&tc_state, &s, s + 1, 0, __ATOMIC_ACQ_REL, __ATOMIC_ACQUIRE))
            continue;
        fn(ctx, i);
        if (__atomic_add_fetch(&tc_finished, 1, __ATOMIC_ACQ_REL) == n) {
            pthread_mutex_lock(&tc_mu);
            if (tc_caller_sleeping)
                pthread_cond_signal(&tc_done);
            pthread_mutex_unlock(&tc_mu);
        }
    }
}

static void *tc_worker(void *arg)
{
    const int id = (int)(long)arg;
    long seen = __atomic_load_n(&tc_state, __ATOMIC_ACQUIRE) >> 32;
    for (;;) {
        /* wait for a loop newer than `seen`: spin a little, then sleep */
        long t0 = tc_now_ns(), epoch;
        for (;;) {
            epoch = __atomic_load_n(&tc_state, __ATOMIC_ACQUIRE) >> 32;
            if (epoch != seen || tc_now_ns() - t0 > TC_SPIN_NS)
                break;
            for (int k = 0; k < 64; ++k)
                tc_relax();
        }
        if (epoch == seen) {
            pthread_mutex_lock(&tc_mu);
            tc_sleeping++;
            while ((epoch = __atomic_load_n(&tc_state, __ATOMIC_ACQUIRE) >> 32) == seen)
                pthread_cond_wait(&tc_work, &tc_mu);
            tc_sleeping--;
            pthread_mutex_unlock(&tc_mu);
        }
        seen = epoch;
        if (id < __atomic_load_n(&tc_want, __ATOMIC_ACQUIRE))
            tc_run_tasks(epoch);
    }
    return NULL;
}

/* workers 0 .. want - 1 exist (fewer if a thread cannot be created: the caller runs the rest) */
static void tc_grow(int want)
{
    if (want > TC_MAX_WORKERS)
        want = TC_MAX_WORKERS;
    pthread_mutex_lock(&tc_mu);
    while (tc_nworkers < want) {
        pthread_attr_t attr;
        pthread_t th;
        sigset_t all, old;
        pthread_attr_init(&attr);
        pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
        sigfillset(&all);
        pthread_sigmask(SIG_SETMASK, &all, &old); /* signals stay with the Python threads */
        int err = pthread_create(&th, &attr, tc_worker, (void *)(long)tc_nworkers);
        pthread_sigmask(SIG_SETMASK, &old, NULL);
        pthread_attr_destroy(&attr);
        if (err)
            break;
        tc_nworkers++;
    }
    pthread_mutex_unlock(&tc_mu);
}

static void tc_after_fork_child(void)
{
    /* the workers did not survive the fork; the locks may have been held by them */
    pthread_mutex_init(&tc_mu, NULL);
    pthread_mutex_init(&tc_submit, NULL);
    pthread_cond_init(&tc_work, NULL);
    pthread_cond_init(&tc_done, NULL);
    tc_nworkers = tc_sleeping = tc_caller_sleeping = 0;
}

static pthread_once_t tc_once = PTHREAD_ONCE_INIT;
static void tc_init(void)
{
    pthread_atfork(NULL, NULL, tc_after_fork_child);
}

void tc_pool_run(long n, int nt, tc_task_fn fn, void *ctx)
{
    if (n <= 0)
        return;
    if (nt > TC_MAX_WORKERS + 1)
        nt = TC_MAX_WORKERS + 1;
    if (nt <= 1 || n == 1 || n > 0x7fffffffL || pthread_mutex_trylock(&tc_submit) != 0) {
        for (long i = 0; i < n; ++i)
            fn(ctx, i);
        return;
    }
    pthread_once(&tc_once, tc_init);
    const int want = (int)(nt - 1 < n - 1 ? nt - 1 : n - 1);
    tc_grow(want);
    __atomic_store_n(&tc_fn, fn, __ATOMIC_RELAXED);
    __atomic_store_n(&tc_ctx, ctx, __ATOMIC_RELAXED);
    __atomic_store_n(&tc_n, n, __ATOMIC_RELAXED);
    __atomic_store_n(&tc_finished, 0, __ATOMIC_RELAXED);
    __atomic_store_n(&tc_want, want, __ATOMIC_RELAXED);
    const long epoch = (__atomic_load_n(&tc_state, __ATOMIC_RELAXED) >> 32) + 1;
    __atomic_store_n(&tc_state, (epoch & 0x7fffffffL) << 32, __ATOMIC_RELEASE);
    const long ep = (epoch & 0x7fffffffL);
    pthread_mutex_lock(&tc_mu);
    if (tc_sleeping)
        pthread_cond_broadcast(&tc_work);
    pthread_mutex_unlock(&tc_mu);
    tc_run_tasks(ep);
    /* wait for the tasks that workers claimed: spin a little, then sleep */
    long t0 = tc_now_ns();
    while (__atomic_load_n(&tc_finished, __ATOMIC_ACQUIRE) < n && tc_now_ns() - t0 <= TC_SPIN_NS)
        for (int k = 0; k < 64; ++k)
            tc_relax();
    if (__atomic_load_n(&tc_finished, __ATOMIC_ACQUIRE) < n) {
        pthread_mutex_lock(&tc_mu);
        tc_caller_sleeping = 1;
        while (__atomic_load_n(&tc_finished, __ATOMIC_ACQUIRE) < n)
            pthread_cond_wait(&tc_done, &tc_mu);
        tc_caller_sleeping = 0;
        pthread_mutex_unlock(&tc_mu);
    }
    pthread_mutex_unlock(&tc_submit);
}

int tc_pool_workers(void)
{
    return __atomic_load_n(&tc_nworkers, __ATOMIC_ACQUIRE);
}

#endif /* TC_POOL_CLIENT */
#endif /* TC_POOL_C */

#if defined(TC_POOL_SCRATCH) && !defined(TC_POOL_SCRATCH_C)
#define TC_POOL_SCRATCH_C /* once, outside the guard of the rest: a client may include this file
                           * first through another (so3.c) without TC_POOL_SCRATCH */
/* (a client that defines TC_POOL_SCRATCH defines _DEFAULT_SOURCE before its first include: mmap's
 * MAP_ANONYMOUS under -std=c99) */
#include <sys/mman.h>

/* Zeroed scratch of `bytes`, mapped for the call and unmapped after it (tc_scratch_free): a
 * malloc'd block of this size (tens of MB) would come from the heap once glibc has raised its
 * mmap threshold to it, and stay resident after free (measured: +0.1 GB of peak RSS in the
 * curvature + d∇ pair at 1M tets). Fresh anonymous pages are zero (no clearing pass); huge pages
 * advised (one fault per 2 MiB: a 72 MB first fill 28 -> 7 ms on a 2-core KVM guest). NULL when
 * the mapping fails. */
static inline void *tc_scratch(size_t bytes)
{
    void *p = mmap(NULL, bytes ? bytes : 1, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (p == MAP_FAILED)
        return NULL;
#ifdef MADV_HUGEPAGE
    madvise(p, bytes ? bytes : 1, MADV_HUGEPAGE);
#endif
    return p;
}

static inline void tc_scratch_free(void *p, size_t bytes)
{
    munmap(p, bytes ? bytes : 1);
}
#endif /* TC_POOL_SCRATCH */
