#![allow(clippy::unwrap_used)]
//! The durable-map commands offline: journaled builds (`build --source`) merge exactly even when
//! they share scans, `retract` and `repose` give the clean builds, `check` reports a sound file.
#![cfg(feature = "cli")]

use crate::common;

use bgkmap::core::{PointFrame, Pose, RawScan};
use bgkmap::io::pcd::{read_pcd, write_pcd_binary};
use common::{build, export_csv, run_fail, run_ok, run_ok_text, simulate};

#[test]
fn journaled_builds_merge_exactly_and_retract_and_repose_give_the_clean_builds() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 6);
    let s = &sim.scans;
    // a holds (r, 1..4), b holds (r, 3..6): two scans in common.
    build(dir, "a.bgkmap", &["--source", "r"], &s[..4]);
    build(dir, "b.bgkmap", &["--source", "r", "--first-seq", "3"], &s[2..]);
    build(dir, "all.bgkmap", &[], s);
    run_ok(dir, ["merge", "a.bgkmap", "b.bgkmap", "--out", "m.bgkmap"]);
    let all = export_csv(dir, "all.bgkmap");
    assert!(export_csv(dir, "m.bgkmap") == all, "the shared scans were not counted once");
    // Without identities the same merge counts them twice.
    build(dir, "a0.bgkmap", &[], &s[..4]);
    build(dir, "b0.bgkmap", &[], &s[2..]);
    run_ok(dir, ["merge", "a0.bgkmap", "b0.bgkmap", "--out", "m0.bgkmap"]);
    assert!(export_csv(dir, "m0.bgkmap") != all);

    run_ok(dir, ["retract", "m.bgkmap", "--scan", "r:5", "--scan", "r:6"]);
    build(dir, "first4.bgkmap", &[], &s[..4]);
    assert!(export_csv(dir, "m.bgkmap") == export_csv(dir, "first4.bgkmap"));
    run_fail(dir, ["retract", "m.bgkmap", "--scan", "r:6"], &["not in the map", "(r, 6)"]);

    // Re-pose (r, 2), a world-frame scan: its points move rigidly with the correction. The clean
    // build gets those moved points in a PCD whose VIEWPOINT is the new pose.
    let (c, sn) = ((0.05f64).cos(), (0.05f64).sin());
    let new_pose = Pose { translation_m: [2.5, 3.25, 0.75], rotation_wxyz: [c, 0.0, 0.0, sn] };
    let cloud = read_pcd(&std::fs::read(dir.join(&s[1])).unwrap()).unwrap();
    let vp = cloud.viewpoint.unwrap();
    let old = RawScan {
        frame: PointFrame::World,
        world_from_sensor: Pose {
            translation_m: [vp[0], vp[1], vp[2]],
            rotation_wxyz: [vp[3], vp[4], vp[5], vp[6]],
        },
        points: cloud.points,
        max_range_m: None,
    };
    let moved = old.reposed(new_pose).unwrap();
    std::fs::write(
        dir.join("moved.pcd"),
        write_pcd_binary(&moved.points, [2.5, 3.25, 0.75, 1.0, 0.0, 0.0, 0.0]),
    )
    .unwrap();
    let pose_arg = format!("r:2=2.5,3.25,0.75,{c:?},0,0,{sn:?}");
    run_ok(dir, ["repose", "m.bgkmap", "--pose", &pose_arg]);
    let clean: Vec<String> = vec![s[0].clone(), "moved.pcd".into(), s[2].clone(), s[3].clone()];
    build(dir, "clean.bgkmap", &[], &clean);
    assert!(
        export_csv(dir, "m.bgkmap") == export_csv(dir, "clean.bgkmap"),
        "re-posing differs from the clean build"
    );

    let report = run_ok_text(dir, ["check", "m.bgkmap", "--json"]);
    assert!(report.contains("\"ok\":true") && report.contains("\"retracted\":2"), "{report}");
    run_fail(dir, ["repose", "m.bgkmap", "--pose", "r:2=0,0,0,2,0,0,0"], &["unit quaternion"]);
    run_fail(dir, ["retract", "m.bgkmap"], &["either a list of scans or a filter"]);
}
