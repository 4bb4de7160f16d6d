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

/// `f` over consecutive chunks of `items` of `chunk` each (the last may be
/// shorter), given each chunk's first index in `items`, in parallel over the
/// current rayon pool when there are at least `min_parallel` items, else in
/// turn; each chunk's results, in order, joined. `f` gives one result per
/// item of its chunk.
pub fn map_chunks_ordered<T, R, F>(items: &[T], chunk: usize, min_parallel: usize, f: F) -> Vec<R>
where
    T: Sync,
    R: Send,
    F: Fn(usize, &[T]) -> Vec<R> + Sync + Send,
{
    let size = chunk.max(1);
    let chunks: Vec<(usize, &[T])> = items.chunks(size).enumerate().map(|(k, c)| (k * size, c)).collect();
    let parts: Vec<Vec<R>> = if items.len() < min_parallel {
        chunks.into_iter().map(|(start, c)| f(start, c)).collect()
    } else {
        chunks.par_iter().map(|&(start, c)| f(start, c)).collect()
    };
    // Sized once: a growing Vec of this size would be moved to new pages at each doubling.
    let mut out = Vec::with_capacity(items.len());
    for part in parts {
        out.extend(part);
    }
    debug_assert_eq!(out.len(), items.len(), "one result per item");
    out
}

/// `items.iter().filter_map(f)`, in order, as the results of consecutive chunks of `chunk`
/// items each (the last may be shorter): in parallel over the current rayon pool when there
/// are at least `min_parallel` items, else in turn. The parts stay apart: each is small, and
/// the caller lays them out once at their total size (a whole image's results gathered in
/// one growing `Vec` would be moved to new pages at each doubling).
pub fn filter_map_parts<T, R, F>(items: &[T], min_parallel: usize, chunk: usize, f: F) -> Vec<Vec<R>>
where
    T: Sync,
    R: Send,
    F: Fn(&T) -> Option<R> + Sync + Send,
{
    let part = |c: &[T]| c.iter().filter_map(&f).collect::<Vec<R>>();
    let size = chunk.max(1);
    if items.len() < min_parallel {
        items.chunks(size).map(part).collect()
    } else {
        items.par_chunks(size).map(part).collect()
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

    #[test]
    fn chunks_joined_in_order_either_way() {
        let items: Vec<u32> = (0..1000).collect();
        // Each chunk's first index given with it: the squares of the indices themselves.
        let squares = |start: usize, c: &[u32]| {
            c.iter()
                .enumerate()
                .map(|(k, v)| {
                    assert_eq!(*v as usize, start + k);
                    u64::from(*v) * u64::from(*v)
                })
                .collect::<Vec<_>>()
        };
        let sequential = map_chunks_ordered(&items, 64, usize::MAX, squares);
        let parallel = map_chunks_ordered(&items, 7, 0, squares);
        assert_eq!(sequential, parallel);
        assert_eq!(sequential.len(), 1000);
        assert_eq!(parallel[999], 998_001);
        assert!(map_chunks_ordered(&[] as &[u32], 8, 0, squares).is_empty());
    }

    #[test]
    fn filtered_parts_in_order_either_way() {
        let items: Vec<u32> = (0..1000).collect();
        let odd_squares = |v: &u32| (v % 2 == 1).then(|| u64::from(*v) * u64::from(*v));
        let want: Vec<u64> = items.iter().filter_map(odd_squares).collect();
        let sequential = filter_map_parts(&items, usize::MAX, 64, odd_squares);
        let parallel = filter_map_parts(&items, 0, 7, odd_squares);
        assert_eq!(sequential.len(), 16);
        assert_eq!(sequential.concat(), want);
        assert_eq!(parallel.concat(), want);
        assert!(filter_map_parts(&[] as &[u32], 0, 8, odd_squares).is_empty());
    }
}
