//! Handing freed memory back to the system after a large request.
//!
//! The service allocates with mimalloc, which keeps the pages a thread
//! freed for that thread's next allocations: right for the many
//! short-lived buffers of a detection, but after a 60 MB mesh or body the
//! pages stay resident while the service idles. After such a request the
//! threads that held it ask mimalloc to give them back.

/// Request bodies (bytes) or meshes (triangles) above which the memory
/// they freed is handed back when they are answered.
pub const LARGE_BODY_BYTES: u64 = 8 << 20;
pub const LARGE_MESH_TRIANGLES: usize = 100_000;

/// How long (ms) mimalloc keeps the pages a thread freed before handing
/// them back to the system: mimalloc 2's default, 10 ms, hands back the
/// feature maps of one pyramid level before the next level asks for them
/// again, and faulting them back in (the kernel zeroing each page) took
/// 14% of a learned-cell scan (one cup photograph, one thread: 406-418 ms
/// at 10, 360-364 at 1,000). mimalloc purges everything freed once the
/// delay after a free runs out, so under a steady stream of requests
/// 1,000 ms still handed the maps back about once a second: eight
/// learned-cell models on two threads took 313.6 and 315.2 ms a
/// photograph at 1,000 (1.2-1.7 s of system time for 40 scans), 304.2
/// and 306.4 at 10,000 (0.5-0.8 s); HOG's 146.9-149.1 either way. The
/// price: mimalloc purges only when it next runs, so after a burst an
/// idle server holds a little more (eight 4 MP photographs at once:
/// 27-32 MiB above idle up to 25 s later, against 11-15 at 1,000).
/// Large requests still hand their pages back at once
/// ([`release_freed_pages`]).
pub const FREED_PAGES_KEPT_MS: i64 = 10_000;

/// mimalloc's `mi_option_purge_delay` (its index in `mimalloc.h`'s
/// `mi_option_t` of version 2, which `libmimalloc-sys` does not name).
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Sets how long freed pages are kept ([`FREED_PAGES_KEPT_MS`]); called
/// first thing by the binaries that allocate with mimalloc.
pub fn keep_freed_pages() {
    // SAFETY: `mi_option_set` takes no pointers and may be called at any
    // time; an option's value is read when mimalloc next purges.
    unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, FREED_PAGES_KEPT_MS as _) }
}

/// Hands the pages that the calling thread freed (and the allocator's
/// abandoned ones) back to the system.
pub fn release_freed_pages() {
    // SAFETY: `mi_collect` takes no pointers; it walks the calling
    // thread's heap and the allocator's own free lists, and may be called
    // from any thread at any time. Where mimalloc is not the global
    // allocator (tests, the training binary) its heaps are nearly empty
    // and this does next to nothing.
    unsafe { libmimalloc_sys::mi_collect(true) }
}

/// [`release_freed_pages`] on this thread now, and on every thread of
/// `pool` as soon as it is free (nothing waits for them: a thread busy
/// with a long job does it after that job).
pub fn release_freed_pages_of(pool: &rayon::ThreadPool) {
    release_freed_pages();
    pool.spawn_broadcast(|_| release_freed_pages());
}
