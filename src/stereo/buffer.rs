//! Large scratch buffers that a call overwrites before it reads them.
//!
//! A matcher's first call in a fresh process (`spinscan disparity` run once) pays for its
//! buffers' memory as well as for its work: the kernel maps and zeroes every page at its
//! first touch. A buffer grown by `Vec::resize` is touched twice — once by the fill, once by
//! the call — and when it held values, they are copied over first. And a buffer sized by the
//! image times the disparity range may ask for more memory than the machine has: `Vec` then
//! aborts the process, which in the daemon would end a scan without a word.

/// Element types whose all-zero bytes are a value: what [`resize_for_overwrite`] may hand out
/// from zeroed memory.
pub(crate) trait Zeroed: Copy + Default {}
impl Zeroed for u8 {}
impl Zeroed for u16 {}

/// The system refused the memory a buffer needed (or its size overflows an address).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Refused;

/// Makes `v` hold `len` elements, for a buffer whose every element the caller writes before
/// it reads it: the values are the old ones or zero, whichever is cheaper.
///
/// Where that needs a new allocation, the old buffer is freed first (its values are not
/// copied) and the new one is taken zeroed from the allocator, which leaves fresh memory
/// untouched (calloc of a fresh mapping writes nothing): its pages are first touched by the
/// caller's own writes. Semi-global matching's volume at full range is 95 MB on Reindeer:
/// the fill had cost its first call ≈ 5 of 63 ms (docs/matcher.md, "The first call"). A
/// refused allocation is returned as [`Refused`] (the caller names what it needed), and `v`
/// is then empty.
pub(crate) fn resize_for_overwrite<T: Zeroed>(v: &mut Vec<T>, len: usize) -> Result<(), Refused> {
    if len <= v.capacity() {
        v.resize(len, T::default());
        return Ok(());
    }
    *v = Vec::new();
    let layout = std::alloc::Layout::array::<T>(len).map_err(|_| Refused)?;
    // SAFETY: `len > capacity ≥ 0` and `T` (u8 or u16) is not zero-sized, so the layout's size
    // is not zero; the memory comes zeroed from the global allocator with `Vec`'s own layout
    // for `len` elements of `T`, and all-zero bytes are a `T` (`Zeroed`), so every element is
    // initialised; a null pointer (refused) is not used.
    unsafe {
        let ptr = std::alloc::alloc_zeroed(layout) as *mut T;
        if ptr.is_null() {
            return Err(Refused);
        }
        *v = Vec::from_raw_parts(ptr, len, len);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resized_buffer_holds_the_length_asked_and_keeps_what_fits() {
        let mut v: Vec<u16> = vec![7; 10];
        resize_for_overwrite(&mut v, 5).unwrap();
        assert_eq!(v, [7; 5]);
        // Within the capacity: the old values where they were, zero beyond.
        resize_for_overwrite(&mut v, 8).unwrap();
        assert_eq!(v, [7, 7, 7, 7, 7, 0, 0, 0]);
        // A new allocation: every element readable, and zero; and it grows as a `Vec` again.
        let big = v.capacity() * 1000 + 3;
        resize_for_overwrite(&mut v, big).unwrap();
        assert_eq!(v.len(), big);
        assert!(v.iter().all(|&x| x == 0));
        v.push(1);
        assert_eq!((v.len(), v[big]), (big + 1, 1));
    }

    #[test]
    fn memory_the_system_cannot_give_is_refused_not_an_abort() {
        let mut v: Vec<u16> = vec![7; 10];
        // More bytes than an address holds, and more than any machine has.
        assert_eq!(resize_for_overwrite(&mut v, usize::MAX / 2), Err(Refused));
        assert!(v.is_empty());
        assert_eq!(resize_for_overwrite(&mut v, 1 << 60), Err(Refused));
        let mut b: Vec<u8> = Vec::new();
        assert_eq!(resize_for_overwrite(&mut b, (1 << 62) + 1), Err(Refused));
        // And the buffer is usable afterwards.
        resize_for_overwrite(&mut v, 4).unwrap();
        assert_eq!(v, [0; 4]);
    }
}
