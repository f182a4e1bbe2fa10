//! `partition_point` without branches for the short sorted arrays the hot
//! loop searches once per ray (the merged BLAS's instance ranges, the
//! lights' CDF).
//!
//! A binary search over a handful of entries takes a branch per level that
//! a random key mispredicts half the time; counting the entries that satisfy
//! the predicate over the whole array is a few vector compares and no
//! branch. Both give the same index for a predicate that holds on a prefix.

/// Up to this many entries the whole array is counted; past it, binary
/// search (its log2 steps are then fewer than the entries' compares).
const LINEAR_MAX: usize = 32;

/// The number of leading entries of `items` for which `pred` holds, where
/// `pred` holds on a prefix of `items` and nowhere after it: what
/// `items.partition_point(pred)` returns.
#[inline(always)]
pub fn partition_point<T>(items: &[T], pred: impl Fn(&T) -> bool) -> usize {
    if items.len() <= LINEAR_MAX {
        items.iter().map(|x| usize::from(pred(x))).sum()
    } else {
        items.partition_point(pred)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Same answer as the standard library's binary search on sorted
        /// arrays of every length around the switch, keys in and between
        /// the entries, with repeats.
        #[test]
        fn agrees_with_the_binary_search(
            mut items in proptest::collection::vec(0u32..50, 0..70),
            key in 0u32..55,
        ) {
            items.sort_unstable();
            prop_assert_eq!(
                partition_point(&items, |&x| x <= key),
                items.partition_point(|&x| x <= key)
            );
        }
    }
}
