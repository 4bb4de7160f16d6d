//! Work spread over the current rayon pool only when there is enough of it.

use rayon::prelude::*;

/// `items.iter().map(f)`, in order: in parallel over the current rayon pool
/// (chunks of at least `min_len`) when there are at least `min_parallel`
/// items, else on the calling thread. Handing work to the pool costs its
/// threads' wake-up, and on a small machine a busy second core is one the
/// camera driver and the DDS transport do not have: a little work is done
/// where it is asked for.
pub fn map_ordered<T, R, F>(items: &[T], min_parallel: usize, min_len: usize, f: F) -> Vec<R>
where
    T: Sync,
    R: Send,
    F: Fn(&T) -> R + Sync + Send,
{
    if items.len() < min_parallel {
        items.iter().map(f).collect()
    } else {
        items.par_iter().with_min_len(min_len.max(1)).map(f).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_in_order_either_way() {
        let items: Vec<u32> = (0..1000).collect();
        let square = |v: &u32| u64::from(*v) * u64::from(*v);
        let sequential = map_ordered(&items, usize::MAX, 1, square);
        let parallel = map_ordered(&items, 0, 7, square);
        assert_eq!(sequential, parallel);
        assert_eq!(parallel[999], 998_001);
        assert!(map_ordered(&[] as &[u32], 0, 1, square).is_empty());
    }
}
