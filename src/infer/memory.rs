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
