//! Worker threads pinned one per CPU.
//!
//! A frame's recovery is spread over a rayon pool. Between frames the pool
//! idles, and on a scheduler that gathers lightly loaded threads onto one CPU
//! (this project's 2-core virtual machines pack idle vCPUs) the woken workers
//! can share one core for the whole of the next frame: two workers then take
//! the one-worker time. Pinning worker `i` to the `i`-th CPU of the process's
//! affinity mask keeps them apart. The mask is respected, so `taskset` or a
//! cpuset given to the process still decides which CPUs it has.

use std::io;

/// The CPUs the calling thread may run on (the process's mask, as inherited), ascending.
pub fn allowed_cpus() -> io::Result<Vec<usize>> {
    // SAFETY: cpu_set_t is plain data; sched_getaffinity writes at most its size.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    let rc = unsafe { libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) };
    if rc != 0 {
        return Err(io::Error::last_os_error());
    }
    let max = 8 * std::mem::size_of::<libc::cpu_set_t>();
    // SAFETY: CPU_ISSET reads the set within its size (cpu < max).
    Ok((0..max).filter(|&cpu| unsafe { libc::CPU_ISSET(cpu, &set) }).collect())
}

/// Pins the calling thread to one CPU.
pub fn pin_current_thread(cpu: usize) -> io::Result<()> {
    if cpu >= 8 * std::mem::size_of::<libc::cpu_set_t>() {
        return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("no CPU {cpu}")));
    }
    // SAFETY: as in allowed_cpus; CPU_SET writes within the set (checked above).
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    unsafe { libc::CPU_SET(cpu, &mut set) };
    let rc = unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) };
    if rc != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

/// A rayon pool of `threads` workers (0: one per allowed CPU), each pinned to
/// the next CPU of the mask in turn when `pin` is set. A worker that cannot be
/// pinned runs unpinned: pinning changes speed, never results.
pub fn thread_pool(threads: usize, pin: bool) -> Result<rayon::ThreadPool, rayon::ThreadPoolBuildError> {
    builder(threads, pin).0.build()
}

/// [`thread_pool`] with the calling thread as its first worker (rayon's
/// `use_current_thread`; the node's processing thread): the parallel parts of
/// the work it does are pushed to its own queue, where it starts on them at
/// once and the other workers take their share, instead of being handed to a
/// pool it then sleeps on until they are done (two thread wake-ups each
/// time). With the CPUs the workers are pinned to, in worker order (empty:
/// unpinned; the calling thread to the first). The calling thread stays in
/// the pool for as long as it runs (rayon keeps its registration), so call it
/// once per thread: an error if the thread is already in a pool.
pub fn pool_on_current_thread(
    threads: usize,
    pin: bool,
) -> Result<(rayon::ThreadPool, Vec<usize>), rayon::ThreadPoolBuildError> {
    let (b, cpus) = builder(threads, pin);
    let pool = b.use_current_thread().build()?;
    // rayon runs the start handler on the threads it starts, not on this one.
    if !cpus.is_empty() {
        let _ = pin_current_thread(cpu_of(&cpus, 0));
    }
    let n = pool.current_num_threads();
    Ok((pool, worker_cpus(&cpus, n)))
}

/// The CPU of worker `i`: the mask's CPUs in turn (`cpus` not empty).
fn cpu_of(cpus: &[usize], i: usize) -> usize {
    cpus[i % cpus.len()]
}

/// The CPU of each of `n` workers (empty when `cpus` is: unpinned).
fn worker_cpus(cpus: &[usize], n: usize) -> Vec<usize> {
    if cpus.is_empty() {
        return vec![];
    }
    (0..n).map(|i| cpu_of(cpus, i)).collect()
}

/// The builder, and the CPUs its workers are pinned to in turn (empty: unpinned).
fn builder(threads: usize, pin: bool) -> (rayon::ThreadPoolBuilder, Vec<usize>) {
    let cpus = if pin {
        allowed_cpus().unwrap_or_default()
    } else {
        vec![]
    };
    let b = rayon::ThreadPoolBuilder::new().num_threads(threads);
    if cpus.is_empty() {
        return (b, cpus);
    }
    let each = cpus.clone();
    (
        b.start_handler(move |i| {
            let _ = pin_current_thread(cpu_of(&each, i));
        }),
        cpus,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pinned_workers_each_run_on_their_cpu() {
        let cpus = allowed_cpus().expect("the affinity mask");
        assert!(!cpus.is_empty());
        let pool = thread_pool(cpus.len().min(4), true).expect("a pool");
        let seen: Vec<(usize, Vec<usize>)> = pool.broadcast(|ctx| (ctx.index(), allowed_cpus().expect("a mask")));
        let each = worker_cpus(&cpus, pool.current_num_threads());
        for (i, mask) in seen {
            assert_eq!(mask, vec![each[i]], "worker {i}");
        }
        // Unpinned workers keep the whole mask.
        let free = thread_pool(1, false).expect("a pool");
        assert_eq!(free.install(|| allowed_cpus().expect("a mask")), cpus);
        assert!(pin_current_thread(1 << 20).is_err());
    }

    #[test]
    fn the_calling_thread_works_in_its_pool() {
        let cpus = allowed_cpus().expect("the affinity mask");
        for pin in [false, true] {
            // A thread of its own: the pool keeps the thread it was built on.
            let (index, threads, ran_on, pinned, again) = std::thread::spawn(move || {
                let (pool, pinned) = pool_on_current_thread(2, pin).expect("a pool");
                // Work asked for on this thread runs in the pool, this thread among its workers.
                let ran_on: Vec<Option<usize>> = {
                    use rayon::prelude::*;
                    (0..64).into_par_iter().map(|_| rayon::current_thread_index()).collect()
                };
                let again = pool_on_current_thread(2, pin).is_err();
                let out = (
                    rayon::current_thread_index(),
                    rayon::current_num_threads(),
                    ran_on,
                    (pinned, allowed_cpus().expect("a mask")),
                    again,
                );
                drop(pool);
                out
            })
            .join()
            .expect("the thread");
            assert_eq!((index, threads), (Some(0), 2));
            assert!(ran_on.iter().all(|i| matches!(i, Some(0) | Some(1))), "{ran_on:?}");
            assert!(again, "a thread already in a pool is refused");
            let (pinned, mask) = pinned;
            if pin {
                assert_eq!(pinned, worker_cpus(&cpus, 2));
                assert_eq!(mask, vec![pinned[0]], "the calling thread pinned to the first");
            } else {
                assert!(pinned.is_empty());
                assert_eq!(mask, cpus);
            }
        }
    }
}
