//! Helpers shared by the unit tests.

/// A small xorshift generator (Marsaglia's 13/7/17): the same sequence from the same seed on
/// every run, for random test inputs. `seed` must not be 0.
pub(crate) fn xorshift(mut seed: u64) -> impl FnMut() -> u64 {
    move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    }
}
