//! Allocator and thread-pool tuning for tensor work.
//!
//! candle allocates a fresh buffer for every op's result. glibc's malloc serves buffers above
//! 128 KiB–32 MiB with `mmap` and returns freed ones to the kernel, so every op of a training
//! step paid for fresh zeroed pages. Keeping freed memory in the heap instead cuts the time of
//! a training run by about a third (`docs/speed.md`, "Why the hot paths look as they do"). The cost:
//! resident memory stays near its peak instead of shrinking between steps.

/// Raises glibc's mmap and trim thresholds so large freed buffers are reused, unless the user
/// set them through the environment (`MALLOC_MMAP_THRESHOLD_`, `MALLOC_TRIM_THRESHOLD_`).
/// Does nothing on other C libraries.
pub fn tune_for_tensors() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const THRESHOLD: libc::c_int = 1 << 30;
        let set = |var: &str, option: libc::c_int, value: libc::c_int| {
            if std::env::var_os(var).is_none() {
                // SAFETY: mallopt only changes allocator parameters; called before any
                // threads of ours allocate heavily, and glibc serialises it internally.
                unsafe {
                    libc::mallopt(option, value);
                }
            }
        };
        set("MALLOC_MMAP_THRESHOLD_", libc::M_MMAP_THRESHOLD, THRESHOLD);
        set("MALLOC_TRIM_THRESHOLD_", libc::M_TRIM_THRESHOLD, THRESHOLD);
        set("MALLOC_TOP_PAD_", libc::M_TOP_PAD, 64 << 20);
    }
}

/// How long (in spin-loop iterations) an idle worker of candle's element-wise thread pool spins
/// before it sleeps, unless the user set `CANDLE_BARRIER_POOL_SPIN_LIMIT`. candle's default,
/// 25,000, keeps a worker spinning for about half a millisecond after every element-wise op: on
/// two cores shared with rayon's workers (the decoder kernel, matmuls) the spinning thread took
/// the core the working one needed, and a training step ran 2–3× slower on two threads than on
/// one (`docs/speed.md`, "Threads").
pub const CANDLE_SPIN_LIMIT: &str = "200";

/// Threads of candle's element-wise pool unless the user set `CANDLE_NUM_THREADS`: one, the
/// calling thread. colf's heavy work runs on rayon's threads (the decoder kernel, the fast
/// renderer, matmuls through `gemm`); the element-wise ops between them are small, and a second
/// pool thread only waited at candle's barrier for the rest of each op (perf: the caller spent
/// about half its samples spinning there). Measured on 2 cores: a training step 99 ms with one
/// pool thread against 106–112 ms with two, and the default encoding 1.62–1.72 s against 1.83 s
/// wall (`docs/speed.md`, "Threads").
pub const CANDLE_POOL_THREADS: &str = "1";

/// Sets [`CANDLE_SPIN_LIMIT`] and [`CANDLE_POOL_THREADS`] for this process unless the environment
/// sets them. Call before any tensor work (candle reads them when its pool starts), while the
/// process has one thread.
pub fn tune_thread_pools() {
    if std::env::var_os("CANDLE_BARRIER_POOL_SPIN_LIMIT").is_none() {
        std::env::set_var("CANDLE_BARRIER_POOL_SPIN_LIMIT", CANDLE_SPIN_LIMIT);
    }
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        std::env::set_var("CANDLE_NUM_THREADS", CANDLE_POOL_THREADS);
    }
}
