//! One seed, many independent streams.

/// SplitMix64 of (seed, stream, counter): independent seeds for every random choice, so a resumed
/// run, a different thread count or a different batch split draws the same numbers.
pub fn derive_seed(seed: u64, stream: u64, counter: u64) -> u64 {
    let mut z = seed
        ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ counter.wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_and_counters_differ_and_are_stable() {
        // Pinned: every run's random draws depend on these values.
        assert_eq!(derive_seed(0, 0, 0), 0);
        assert_eq!(derive_seed(1, 2, 3), derive_seed(1, 2, 3));
        assert_ne!(derive_seed(1, 2, 3), derive_seed(1, 3, 2));
        assert_ne!(derive_seed(1, 2, 3), derive_seed(2, 2, 3));
    }
}
