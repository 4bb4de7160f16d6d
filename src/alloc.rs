//! The binary's global allocator: allocations of [`LARGE`] bytes and more get
//! an anonymous mapping of their own (`mmap`; `mremap` when they grow;
//! `munmap` when freed), everything smaller goes to the system allocator.
//!
//! Why: the node publishes about 0.6 MB a frame that RustDDS keeps for up to
//! 6 s, in buffers grown by `realloc` (serialization into a `Vec`). glibc
//! grows such a buffer inside its malloc arenas when it can, and over
//! minutes the arenas fragment: resident memory climbs while the bytes in
//! live allocations stay flat (README, The node). A buffer in a mapping of
//! its own is handed back to the kernel when it is freed. Linux only;
//! elsewhere everything goes to the system allocator.
//!
//! A mapping's length is its size class ([`mapping_len`]: four classes to
//! each doubling, so at most a quarter more than asked). A freed mapping is
//! first kept in a small cache ([`CACHE_SLOTS`] mappings, at most
//! [`CACHE_BYTES`] in all, the oldest handed back first) and reused by the next
//! allocation of the same class: the pipeline's per-frame buffers come back
//! every frame at sizes that follow the objects in view (a region's pixels),
//! so from one frame to the next a buffer's size moves within its class, and a
//! fresh mapping costs a page fault for each page it touches. The cache bounds
//! what is kept, so resident memory stays flat.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

/// Smallest allocation given a mapping of its own, bytes.
pub const LARGE: usize = 64 * 1024;

/// Page size the mappings are rounded to (mmap's alignment on Linux).
const PAGE: usize = 4096;

/// Bytes in mappings of this allocator now.
static MAPPED: AtomicUsize = AtomicUsize::new(0);

/// Bytes currently held in this allocator's own mappings by live
/// allocations (0 off Linux; the cache's are [`cached_bytes`]).
pub fn mapped_bytes() -> usize {
    MAPPED.load(Ordering::Relaxed)
}

/// Most freed mappings kept for reuse.
pub const CACHE_SLOTS: usize = 64;

/// Most bytes kept in freed mappings for reuse; a larger mapping is handed back at once.
pub const CACHE_BYTES: usize = 64 << 20;

/// Bytes in freed mappings kept for reuse.
static CACHED: AtomicUsize = AtomicUsize::new(0);

/// Bytes in freed mappings kept for reuse now (resident, not live).
pub fn cached_bytes() -> usize {
    CACHED.load(Ordering::Relaxed)
}

/// Freed mappings `(address, length)`, oldest first.
struct Cache {
    slots: [(usize, usize); CACHE_SLOTS],
    len: usize,
    bytes: usize,
}

static CACHE: Mutex<Cache> = Mutex::new(Cache {
    slots: [(0, 0); CACHE_SLOTS],
    len: 0,
    bytes: 0,
});

fn cache() -> std::sync::MutexGuard<'static, Cache> {
    // Nothing panics while the lock is held; a poisoned lock still holds a consistent cache.
    CACHE.lock().unwrap_or_else(|e| e.into_inner())
}

/// A cached mapping of exactly `len` bytes (the newest such), taken out of the cache.
fn take_cached(len: usize) -> Option<*mut u8> {
    let mut c = cache();
    let n = c.len;
    let k = (0..n).rev().find(|&k| c.slots[k].1 == len)?;
    let (addr, _) = c.slots[k];
    c.slots.copy_within(k + 1..n, k);
    c.len -= 1;
    c.bytes -= len;
    CACHED.fetch_sub(len, Ordering::Relaxed);
    MAPPED.fetch_add(len, Ordering::Relaxed);
    Some(addr as *mut u8)
}

/// Keeps the freed mapping `p` of `len` bytes for reuse, handing back the
/// oldest ones to make room; `false` (nothing kept) when it is too large.
fn keep_cached(p: *mut u8, len: usize) -> bool {
    if len > CACHE_BYTES / 2 {
        return false;
    }
    let mut evicted = [(0usize, 0usize); CACHE_SLOTS];
    let mut n_evicted = 0;
    {
        let mut c = cache();
        while c.len == CACHE_SLOTS || c.bytes + len > CACHE_BYTES {
            let oldest = c.slots[0];
            let n = c.len;
            c.slots.copy_within(1..n, 0);
            c.len -= 1;
            c.bytes -= oldest.1;
            evicted[n_evicted] = oldest;
            n_evicted += 1;
        }
        let n = c.len;
        c.slots[n] = (p as usize, len);
        c.len += 1;
        c.bytes += len;
        MAPPED.fetch_sub(len, Ordering::Relaxed);
        CACHED.fetch_add(len, Ordering::Relaxed);
    }
    for &(addr, l) in &evicted[..n_evicted] {
        CACHED.fetch_sub(l, Ordering::Relaxed);
        // SAFETY: an evicted mapping of `l` bytes, no longer in the cache or in use.
        unsafe { unmap_raw(addr as *mut u8, l) };
    }
    true
}

/// Bytes of free memory glibc may keep at the top of its heaps before handing
/// it back ([`keep_heap_tops`]).
pub const HEAP_TOP_KEPT: usize = 32 << 20;

/// Lets glibc keep up to [`HEAP_TOP_KEPT`] bytes free at the top of its heaps
/// (`M_TRIM_THRESHOLD`; its default is 128 KiB). The pipeline's small
/// per-frame buffers (under [`LARGE`], so not in mappings of their own) are
/// freed at the end of each frame; glibc then handed the heap's top back to
/// the kernel, and the next frame paid a page fault for each page again (7 %
/// of `bench --cases recover`'s samples, in the kernel). The memory kept is
/// what the frames themselves use: it is not allocated, only not returned.
/// Call it first in `main`, before any thread starts; nothing off glibc.
pub fn keep_heap_tops() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets one of glibc's parameters; called before other threads exist.
    unsafe {
        libc::mallopt(libc::M_TRIM_THRESHOLD, HEAP_TOP_KEPT as libc::c_int);
    }
}

/// Large allocations in mappings of their own, the rest from [`System`].
pub struct LargeMapped;

#[cfg(target_os = "linux")]
fn is_large(layout: &Layout) -> bool {
    layout.size() >= LARGE && layout.align() <= PAGE
}

#[cfg(not(target_os = "linux"))]
fn is_large(_: &Layout) -> bool {
    false
}

/// Size classes to each doubling of a mapping's length.
const CLASSES_PER_DOUBLING: usize = 4;

/// The length of the mapping that holds `bytes`: the smallest of `2^k`,
/// `1.25 * 2^k`, `1.5 * 2^k` and `1.75 * 2^k` pages that holds them, so that
/// buffers whose sizes differ a little from frame to frame share a class (and a
/// cached mapping). At most a quarter more than the pages asked for.
fn mapping_len(bytes: usize) -> usize {
    let pages = bytes.div_ceil(PAGE).max(1);
    if pages <= CLASSES_PER_DOUBLING {
        return pages * PAGE;
    }
    // The class step: a quarter of the largest power of two not above `pages`.
    let step = (1usize << pages.ilog2()) / CLASSES_PER_DOUBLING;
    pages.div_ceil(step) * step * PAGE
}

#[cfg(target_os = "linux")]
unsafe fn map(len: usize) -> *mut u8 {
    // SAFETY: an anonymous private mapping of `len` bytes, no file.
    let p = unsafe {
        libc::mmap(
            std::ptr::null_mut(),
            len,
            libc::PROT_READ | libc::PROT_WRITE,
            libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
            -1,
            0,
        )
    };
    if p == libc::MAP_FAILED {
        return std::ptr::null_mut();
    }
    MAPPED.fetch_add(len, Ordering::Relaxed);
    p.cast()
}

#[cfg(not(target_os = "linux"))]
unsafe fn map(_: usize) -> *mut u8 {
    std::ptr::null_mut()
}

/// Frees a live mapping: into the cache, or back to the kernel.
unsafe fn unmap(p: *mut u8, len: usize) {
    if !keep_cached(p, len) {
        // SAFETY: `p` is a mapping of `len` bytes made by `map` or `remap`.
        unsafe { unmap_raw(p, len) };
        MAPPED.fetch_sub(len, Ordering::Relaxed);
    }
}

#[cfg(target_os = "linux")]
unsafe fn unmap_raw(p: *mut u8, len: usize) {
    // SAFETY: `p` is a mapping of `len` bytes made by `map` or `remap`.
    unsafe { libc::munmap(p.cast(), len) };
}

#[cfg(not(target_os = "linux"))]
unsafe fn unmap_raw(_: *mut u8, _: usize) {}

#[cfg(target_os = "linux")]
unsafe fn remap(p: *mut u8, old: usize, new: usize) -> *mut u8 {
    // SAFETY: `p` is a mapping of `old` bytes made by `map` or `remap`; the kernel may move it.
    let q = unsafe { libc::mremap(p.cast(), old, new, libc::MREMAP_MAYMOVE) };
    if q == libc::MAP_FAILED {
        return std::ptr::null_mut();
    }
    MAPPED.fetch_add(new, Ordering::Relaxed);
    MAPPED.fetch_sub(old, Ordering::Relaxed);
    q.cast()
}

#[cfg(not(target_os = "linux"))]
unsafe fn remap(_: *mut u8, _: usize, _: usize) -> *mut u8 {
    std::ptr::null_mut()
}

// SAFETY: every pointer goes back to the allocator that made it: a layout is
// large or not by its size and alignment, which `dealloc` and `realloc` are
// given unchanged (GlobalAlloc's contract), and a reallocation that crosses
// `LARGE` copies into the other allocator and frees the old block.
unsafe impl GlobalAlloc for LargeMapped {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if is_large(&layout) {
            let len = mapping_len(layout.size());
            match take_cached(len) {
                Some(p) => p,
                // SAFETY: a fresh mapping; page alignment covers `layout.align()`.
                None => unsafe { map(len) },
            }
        } else {
            // SAFETY: forwarded with the caller's layout.
            unsafe { System.alloc(layout) }
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if is_large(&layout) {
            let len = mapping_len(layout.size());
            match take_cached(len) {
                Some(p) => {
                    // SAFETY: a cached mapping of `len >= layout.size()` bytes, now this block's.
                    unsafe { std::ptr::write_bytes(p, 0, layout.size()) };
                    p
                }
                // SAFETY: anonymous mappings are zero-filled.
                None => unsafe { map(len) },
            }
        } else {
            // SAFETY: forwarded with the caller's layout.
            unsafe { System.alloc_zeroed(layout) }
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if is_large(&layout) {
            // SAFETY: a large layout's block is a mapping of these pages.
            unsafe { unmap(ptr, mapping_len(layout.size())) }
        } else {
            // SAFETY: a small layout's block came from System.
            unsafe { System.dealloc(ptr, layout) }
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: GlobalAlloc::realloc guarantees `new_size`, rounded to the alignment, fits isize.
        let new_layout = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
        match (is_large(&layout), is_large(&new_layout)) {
            // SAFETY: both small: System's own block, resized by System.
            (false, false) => unsafe { System.realloc(ptr, layout, new_size) },
            (true, true) => {
                let (old, new) = (mapping_len(layout.size()), mapping_len(new_size));
                if old == new {
                    return ptr;
                }
                // SAFETY: `ptr` is a mapping of `old` bytes.
                unsafe { remap(ptr, old, new) }
            }
            _ => {
                // Crossing the threshold: a block from the other side, the contents copied.
                // SAFETY: `new_layout` is valid (above); the old block is freed with its own layout.
                unsafe {
                    let q = self.alloc(new_layout);
                    if !q.is_null() {
                        std::ptr::copy_nonoverlapping(ptr, q, layout.size().min(new_size));
                        self.dealloc(ptr, layout);
                    }
                    q
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_keep_their_contents_across_the_threshold() {
        let a = LargeMapped;
        let small = Layout::from_size_align(1000, 8).unwrap();
        // SAFETY: each block is used within its size and freed once with its layout.
        unsafe {
            let p = a.alloc(small);
            assert!(!p.is_null());
            for i in 0..1000 {
                *p.add(i) = (i % 251) as u8;
            }
            // Small -> large -> larger (mremap) -> small again.
            let q = a.realloc(p, small, 100_000);
            let large = Layout::from_size_align(100_000, 8).unwrap();
            assert!(!q.is_null());
            for i in 0..1000 {
                assert_eq!(*q.add(i), (i % 251) as u8);
            }
            *q.add(99_999) = 7;
            let r = a.realloc(q, large, 3_000_000);
            let larger = Layout::from_size_align(3_000_000, 8).unwrap();
            assert!(!r.is_null());
            assert_eq!((*r.add(500), *r.add(99_999)), ((500 % 251) as u8, 7));
            #[cfg(target_os = "linux")]
            assert!(mapped_bytes() >= 3_000_000);
            let s = a.realloc(r, larger, 600);
            assert!(!s.is_null());
            assert_eq!(*s.add(599), (599 % 251) as u8);
            a.dealloc(s, Layout::from_size_align(600, 8).unwrap());
            // A zeroed large block is zero.
            let z = a.alloc_zeroed(large);
            assert!((0..100_000).all(|i| *z.add(i) == 0));
            a.dealloc(z, large);
        }
    }

    #[test]
    fn a_mapping_is_the_smallest_class_that_holds_the_block() {
        assert_eq!(mapping_len(LARGE), LARGE);
        assert_eq!(mapping_len(LARGE + 1), 20 * PAGE);
        assert_eq!(mapping_len(3 * PAGE), 3 * PAGE);
        // 193..=224 pages share the class of 224 (1.75 * 128).
        assert_eq!(mapping_len(193 * PAGE), 224 * PAGE);
        assert_eq!(mapping_len(224 * PAGE), 224 * PAGE);
        assert_eq!(mapping_len(224 * PAGE + 1), 256 * PAGE);
        for bytes in (LARGE..40 * LARGE).step_by(4093) {
            let len = mapping_len(bytes);
            assert!(len >= bytes && len.is_multiple_of(PAGE), "{bytes} in {len}");
            assert!(len <= bytes.div_ceil(PAGE) * PAGE * 5 / 4, "{bytes} in {len}");
        }
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn freed_mappings_are_reused_by_class_and_the_oldest_handed_back() {
        let a = LargeMapped;
        // Sizes in one class (224 pages) no other test uses (the cache is shared).
        let layout = |k: usize| Layout::from_size_align((197 + k % 23) * PAGE + 8, 8).unwrap();
        // SAFETY: each block is used within its size and freed once with its layout.
        unsafe {
            let p = a.alloc(layout(0));
            std::ptr::write_bytes(p, 0xab, layout(0).size());
            a.dealloc(p, layout(0));
            // Another size of the same class comes back from the cache, zeroed when asked.
            let q = a.alloc_zeroed(layout(5));
            assert_eq!(q, p);
            assert!((0..layout(5).size()).all(|i| *q.add(i) == 0));
            a.dealloc(q, layout(5));
            // Past CACHE_SLOTS freed mappings, the oldest are handed back.
            let blocks: Vec<*mut u8> = (1..=CACHE_SLOTS + 4).map(|k| a.alloc(layout(k))).collect();
            for (k, &b) in (1..).zip(&blocks) {
                a.dealloc(b, layout(k));
            }
            assert!(cached_bytes() <= CACHE_BYTES);
            {
                let c = cache();
                assert!(c.len <= CACHE_SLOTS);
                assert!(
                    c.slots[..c.len].iter().all(|&(addr, _)| addr != blocks[0] as usize),
                    "the oldest is gone"
                );
            }
            let newest = blocks[CACHE_SLOTS + 3];
            assert_eq!(
                take_cached(mapping_len(layout(1).size())),
                Some(newest),
                "the newest is kept"
            );
            a.dealloc(newest, layout(CACHE_SLOTS + 4));
            // Too large for the cache: handed back at once.
            let big = Layout::from_size_align(CACHE_BYTES / 2 + PAGE, 8).unwrap();
            let before = cached_bytes();
            let c = a.alloc(big);
            a.dealloc(c, big);
            assert!(cached_bytes() <= before);
        }
    }
}
