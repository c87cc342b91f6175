//! PLY reading on the real Stanford bunny files (`../shared/data/stanford-bunny-scans`): CRLF
//! headers, `obj_info` lines, the `range_grid` list element after the vertices, and the
//! zippered mesh's faces — what registration will read.

mod support;

use spinscan::io::ply::{read_ply, write_ply};

#[test]
fn reads_range_scans_with_crlf_and_range_grid() {
    let dir = support::shared_data("stanford-bunny-scans");
    let scan = read_ply(&dir.join("bun045.ply")).unwrap();
    assert_eq!(scan.cloud.len(), 40097);
    assert!(scan.triangles.is_empty());
    // The scans are in metres, about 0.1–0.2 m across.
    let extent = scan.cloud.points.iter().fold([f32::MAX, f32::MIN], |[lo, hi], p| [lo.min(p[0]), hi.max(p[0])]);
    assert!(extent[1] - extent[0] > 0.05 && extent[1] - extent[0] < 0.3, "{extent:?}");
    // ear_back.ply has LF line endings: both kinds read.
    assert!(read_ply(&dir.join("ear_back.ply")).unwrap().cloud.len() > 1000);
}

#[test]
fn reads_the_zippered_mesh_and_round_trips_it() {
    let dir = support::shared_data("stanford-bunny-scans");
    let mesh = read_ply(&dir.join("bun_zipper.ply")).unwrap();
    assert_eq!(mesh.cloud.len(), 35947);
    assert_eq!(mesh.triangles.len(), 69451);
    let tmp = support::temp_dir("ply-bunny");
    write_ply(&tmp.join("b.ply"), &mesh.cloud).unwrap();
    let back = read_ply(&tmp.join("b.ply")).unwrap();
    assert_eq!(back.cloud.points, mesh.cloud.points);
}
