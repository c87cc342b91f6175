//! Large scratch buffers that a call overwrites before it reads them.
//!
//! A matcher's first call in a fresh process (`spinscan disparity` run once) pays for its
//! buffers' memory as well as for its work: the kernel maps and zeroes every page at its
//! first touch. A buffer grown by `Vec::resize` is touched twice — once by the fill, once by
//! the call — and when it held values, they are copied over first.

/// Makes `v` hold `len` elements, for a buffer whose every element the caller writes before
/// it reads it: the values are the old ones or zero, whichever is cheaper.
///
/// Where that needs a new allocation, the old buffer is freed first (its values are not
/// copied) and the new one is taken zeroed from the allocator, which leaves fresh memory
/// untouched (calloc of a fresh mapping writes nothing): its pages are first touched by the
/// caller's own writes. Semi-global matching's volume at full range is 95 MB on Reindeer:
/// the fill had cost its first call ≈ 5 of 63 ms (docs/matcher.md, "The first call").
pub(crate) fn resize_for_overwrite<T: Copy + Default>(v: &mut Vec<T>, len: usize) {
    if len <= v.capacity() {
        v.resize(len, T::default());
        return;
    }
    *v = Vec::new();
    *v = vec![T::default(); len];
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resized_buffer_holds_the_length_asked_and_keeps_what_fits() {
        let mut v: Vec<u16> = vec![7; 10];
        resize_for_overwrite(&mut v, 5);
        assert_eq!(v, [7; 5]);
        // Within the capacity: the old values where they were, zero beyond.
        resize_for_overwrite(&mut v, 8);
        assert_eq!(v, [7, 7, 7, 7, 7, 0, 0, 0]);
        // A new allocation: every element readable, and zero.
        let big = v.capacity() * 1000 + 3;
        resize_for_overwrite(&mut v, big);
        assert_eq!(v.len(), big);
        assert!(v.iter().all(|&x| x == 0));
    }
}
