//! Large read-only arrays that rays read at random (the BVH's nodes and
//! triangle packets, per-triangle shading normals) on 2 MiB pages where
//! Linux offers them.
//!
//! A closest-hit or shadow ray visits a few nodes and leaves scattered over
//! arrays of tens of MiB (20 MiB for the default scene's knot). With 4 KiB
//! pages nearly every visit is also a TLB miss and a page walk; with 2 MiB
//! pages the whole tree fits the TLB. Linux's transparent huge pages are
//! often enabled only for memory that asks (`madvise`, the default of many
//! distributions), and only for pages not yet touched, which the allocator's
//! recycled heap memory seldom is. So a large array gets a fresh anonymous
//! mapping of its own, advised before anything is written to it; the kernel
//! backs its 2 MiB-aligned part with huge pages as it is filled. Elsewhere,
//! or where the kernel declines, only speed differs.

use std::ops::Deref;

/// Arrays smaller than this stay ordinary vectors (small trees stay in the
/// caches anyway).
const MIN_BYTES: usize = 4 << 20;

/// The huge page size (x86-64 and AArch64 with 4 KiB base pages).
#[cfg(target_os = "linux")]
const HUGE: usize = 2 << 20;

/// A read-only array, in its own huge-page-advised mapping when large.
pub(crate) enum HugeArray<T: Copy> {
    Plain(Vec<T>),
    #[cfg(target_os = "linux")]
    Mapped {
        /// The array: the mapping's first 2 MiB boundary.
        ptr: *const T,
        len: usize,
        /// The whole mapping, for `munmap`.
        base: *mut libc::c_void,
        map_bytes: usize,
    },
}

// SAFETY: a `Mapped` array owns its mapping exclusively and is never
// written after construction; it is as shareable as a `Vec<T>` of the same
// items.
unsafe impl<T: Copy + Send> Send for HugeArray<T> {}
unsafe impl<T: Copy + Sync> Sync for HugeArray<T> {}

impl<T: Copy> HugeArray<T> {
    /// `items`, moved into a huge-page-advised mapping when it is large
    /// enough and the platform has one (else kept as it is).
    pub(crate) fn new(items: Vec<T>) -> Self {
        match Self::mapped(&items) {
            Some(a) => a,
            None => Self::Plain(items),
        }
    }

    /// A copy of `items`, as [`HugeArray::new`] would hold it, without
    /// first copying them into a vector of their own.
    pub(crate) fn from_slice(items: &[T]) -> Self {
        Self::mapped(items).unwrap_or_else(|| Self::Plain(items.to_vec()))
    }

    /// `items` copied into a fresh mapping advised for huge pages; `None`
    /// when they are too small to be worth one, or no mapping was made.
    #[cfg(target_os = "linux")]
    fn mapped(items: &[T]) -> Option<Self> {
        let bytes = std::mem::size_of_val(items);
        if bytes < MIN_BYTES {
            return None;
        }
        // Room to start the array on a 2 MiB boundary, so that all of it
        // can be huge pages.
        let map_bytes = bytes + HUGE;
        // SAFETY: an anonymous private mapping of `map_bytes` bytes, checked
        // for failure before use.
        let base = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                map_bytes,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                -1,
                0,
            )
        };
        if base == libc::MAP_FAILED {
            return None;
        }
        let aligned = (base as usize).next_multiple_of(HUGE);
        // SAFETY: [base, base + map_bytes) is the mapping just made, and
        // [aligned, aligned + bytes) lies inside it; it is not yet touched,
        // so the advice takes effect as the copy below faults it in. A
        // refusal (THP disabled) leaves ordinary pages and is ignored. The
        // destination is suitably aligned for T (2 MiB) and does not overlap
        // `items`.
        unsafe {
            libc::madvise(aligned as *mut libc::c_void, bytes, libc::MADV_HUGEPAGE);
            std::ptr::copy_nonoverlapping(items.as_ptr(), aligned as *mut T, items.len());
        }
        Some(Self::Mapped {
            ptr: aligned as *const T,
            len: items.len(),
            base,
            map_bytes,
        })
    }

    #[cfg(not(target_os = "linux"))]
    fn mapped(_items: &[T]) -> Option<Self> {
        None
    }
}

/// Asks Linux to back the 2 MiB-aligned part of an array that already
/// holds its data (an estimator's grids, loaded from its file) with huge
/// pages now: `MADV_COLLAPSE` (Linux 6.1 and later) copies the pages it can
/// into huge ones synchronously; older kernels refuse it, and then only
/// speed differs. Arrays below [`MIN_BYTES`] are left alone.
pub(crate) fn collapse(bytes: &[u8]) {
    if bytes.len() < MIN_BYTES {
        return;
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let start = (bytes.as_ptr() as usize).next_multiple_of(HUGE);
        let end = (bytes.as_ptr() as usize + bytes.len()) / HUGE * HUGE;
        if end > start {
            // SAFETY: [start, end) lies inside `bytes`, memory this process
            // owns and keeps mapped for the call. Both advices change only
            // how the kernel backs those pages (a collapse copies their
            // contents into a huge page), never what they hold; a refusal
            // leaves them as they were, so the results are ignored.
            unsafe {
                libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
                libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_COLLAPSE);
            }
        }
    }
}

impl<T: Copy> Deref for HugeArray<T> {
    type Target = [T];

    #[inline(always)]
    fn deref(&self) -> &[T] {
        match self {
            Self::Plain(v) => v,
            // SAFETY: `len` items were copied to `ptr` in `mapped`, and the
            // mapping lives until `drop`.
            #[cfg(target_os = "linux")]
            Self::Mapped { ptr, len, .. } => unsafe { std::slice::from_raw_parts(*ptr, *len) },
        }
    }
}

impl<T: Copy> Drop for HugeArray<T> {
    fn drop(&mut self) {
        #[cfg(target_os = "linux")]
        if let Self::Mapped {
            base, map_bytes, ..
        } = *self
        {
            // SAFETY: the mapping made in `mapped`, unmapped once; no slice
            // of it outlives `self`. (T is Copy: nothing to drop in it.)
            unsafe {
                libc::munmap(base, map_bytes);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_keep_their_contents_whatever_their_size() {
        for n in [0usize, 1, 1000, MIN_BYTES / 4 + 12_345, (5 << 20) / 4] {
            let v: Vec<u32> = (0..n as u32)
                .map(|i| i.wrapping_mul(2_654_435_761))
                .collect();
            let a = HugeArray::new(v.clone());
            assert_eq!(&a[..], &v[..]);
            assert_eq!(&HugeArray::from_slice(&v)[..], &v[..]);
            assert_eq!(a.as_ptr() as usize % std::mem::align_of::<u32>(), 0);
        }
    }

    #[test]
    fn collapsing_keeps_an_array_s_contents() {
        let v: Vec<u8> = (0..(9usize << 20)).map(|i| (i * 31 % 251) as u8).collect();
        let copy = v.clone();
        collapse(&v);
        assert_eq!(v, copy);
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn large_arrays_get_their_own_mapping_on_a_huge_page_boundary() {
        let a = HugeArray::new(vec![7u64; MIN_BYTES / 8 + 1]);
        assert!(matches!(a, HugeArray::Mapped { .. }));
        assert_eq!(a.as_ptr() as usize % (2 << 20), 0);
        assert!(a.iter().all(|&x| x == 7));
    }
}
