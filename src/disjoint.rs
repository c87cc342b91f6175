//! Disjoint sets as a parent array (union–find): the root of an element's set, with path
//! halving. Shared by the speckle filter (runs of pixels) and the mesh clean-up (vertices,
//! triangles round a vertex).

/// The root of `v`'s set in `parent` (an element is a root when it is its own parent);
/// every element met on the way is pointed at its grandparent.
#[inline]
pub(crate) fn root(parent: &mut [u32], mut v: u32) -> u32 {
    while parent[v as usize] != v {
        let up = parent[parent[v as usize] as usize];
        parent[v as usize] = up;
        v = up;
    }
    v
}
