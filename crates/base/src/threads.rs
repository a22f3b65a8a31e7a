//! Thread counts where a setting of 0 means "all cores".

/// The number of cores this process may use (`std::thread::available_parallelism`; 1 if unknown).
pub fn available_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// A thread-count setting resolved: `0` means all cores ([`available_cores`]), any other value
/// is taken as given.
pub fn threads(setting: usize) -> usize {
    match setting {
        0 => available_cores(),
        n => n,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_means_all_cores_and_others_pass_through() {
        assert!(available_cores() >= 1);
        assert_eq!(threads(0), available_cores());
        assert_eq!(threads(3), 3);
        assert_eq!(threads(1), 1);
    }
}
