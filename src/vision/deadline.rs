//! A point in time after which a computation gives up: every long loop of
//! the detector and of the pose refinement asks it, so that no request
//! holds the worker past its deadline whatever its input.

use std::time::Instant;

/// When a computation must stop; `Deadline::NONE` never passes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Deadline(Option<Instant>);

impl Deadline {
    /// No deadline (offline tools, tests).
    pub const NONE: Deadline = Deadline(None);

    /// A deadline at `at`.
    pub fn at(at: Instant) -> Self {
        Self(Some(at))
    }

    /// The instant, if any.
    pub fn instant(&self) -> Option<Instant> {
        self.0
    }

    /// Whether the deadline has passed.
    #[inline]
    pub fn passed(&self) -> bool {
        self.0.is_some_and(|t| Instant::now() >= t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn none_never_passes_and_a_past_instant_has() {
        assert!(!Deadline::NONE.passed());
        assert!(!Deadline::default().passed());
        let now = Instant::now();
        assert!(Deadline::at(now).passed());
        assert!(!Deadline::at(now + Duration::from_secs(3600)).passed());
        assert_eq!(Deadline::at(now).instant(), Some(now));
    }
}
