//! A request to stop a long call early (a front end's Ctrl-C), shared between the thread that
//! asks and the threads doing the work.
//!
//! Long loops (training's gradient steps, collection's episodes) check it between units of work
//! that leave nothing half done, and return their crate's `Interrupted` error: what was committed
//! before stays valid (a run resumes from its last checkpoint; a collection's finished files are
//! whole). The flag is not part of any configuration: two configurations that differ only in it
//! compare equal, and it is never serialised.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// A shared stop request; clones see the same flag. The default is never set (nobody asks).
#[derive(Debug, Clone, Default)]
pub struct StopFlag(Arc<AtomicBool>);

impl StopFlag {
    /// Asks every holder to stop.
    pub fn set(&self) {
        self.0.store(true, Ordering::Relaxed);
    }

    /// Whether a stop was asked for.
    pub fn is_set(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

/// A stop request does not make two settings different (configurations carry one only so that it
/// reaches their loops).
impl PartialEq for StopFlag {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::StopFlag;

    #[test]
    fn clones_share_the_flag() {
        let a = StopFlag::default();
        let b = a.clone();
        assert!(!b.is_set());
        a.set();
        assert!(b.is_set());
        assert_eq!(StopFlag::default(), a);
    }
}
