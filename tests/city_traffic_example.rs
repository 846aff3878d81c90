//! `examples/city_traffic.rs` (make demo-city's merge): the script it writes, applied by
//! colf-edit, lines every slot of several codes files up in the lanes, turned to its side's way.

mod common;

use colf::codes::{Codes, Slot};
use glam::{DMat4, DVec3};
use std::path::PathBuf;
use std::process::Command;

/// The example's binary, built beside the test binaries by `cargo test`.
fn example() -> PathBuf {
    let deps = std::env::current_exe().unwrap();
    let profile = deps.parent().unwrap().parent().unwrap();
    profile.join("examples").join("city_traffic")
}

fn street(xs: &[(f64, f64)]) -> Codes {
    Codes {
        slots: xs
            .iter()
            .enumerate()
            .map(|(i, &(x, y))| Slot {
                latent: vec![i as f32; 4],
                slot_to_world: DMat4::from_translation(DVec3::new(x, y, 0.4)),
                mass: 0.1,
                source: format!("v.png#{i}"),
            })
            .collect(),
        background: vec![0.0; 4],
        model: "m".into(),
    }
}

#[test]
fn slots_of_several_streets_are_lined_up_in_the_lanes() {
    let dir = tempfile::tempdir().unwrap();
    let paths: Vec<String> = [
        street(&[(95.0, -1.8), (101.0, 1.8)]),
        street(&[(30.0, -1.7), (50.0, 1.9), (52.0, 1.6)]),
    ]
    .iter()
    .enumerate()
    .map(|(i, codes)| {
        let path = dir.path().join(format!("s{i}.codes"));
        codes.write(path.to_str().unwrap()).unwrap();
        path.to_str().unwrap().to_string()
    })
    .collect();
    let out = Command::new(example())
        .args(["--lanes", "-2,2", "--from", "0", "--to", "20"])
        .args(&paths)
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let script = dir.path().join("edits.json");
    std::fs::write(&script, &out.stdout).unwrap();
    let merged = dir.path().join("merged.codes");
    let edit = Command::new(env!("CARGO_BIN_EXE_colf-edit"))
        .arg(&script)
        .arg(&paths[0])
        .arg("-o")
        .arg(&merged)
        .output()
        .unwrap();
    assert!(edit.status.success(), "{edit:?}");
    let codes = Codes::read(merged.to_str().unwrap()).unwrap();
    // Five slots, in order of their x along their streets, two lanes, three places 10 apart.
    let want = [
        ("v.png#0", 0.0, -2.0),  // x 30 (street 1)
        ("v.png#1", 0.0, 2.0),   // x 50
        ("v.png#2", 10.0, -2.0), // x 52
        ("v.png#0", 10.0, 2.0),  // x 95 (street 0)
        ("v.png#1", 20.0, -2.0), // x 101
    ];
    let mut placed: Vec<(String, f64, f64, f64)> = codes
        .slots
        .iter()
        .map(|s| {
            let o = s.slot_to_world.w_axis;
            // Heading: where the slot's own x axis points in the world.
            (s.source.clone(), o.x, o.y, s.slot_to_world.x_axis.x)
        })
        .collect();
    placed.sort_by(|a, b| (a.1, a.2).partial_cmp(&(b.1, b.2)).unwrap());
    assert_eq!(placed.len(), want.len());
    for ((source, x, y, _), (want_source, wx, wy)) in placed.iter().zip(want) {
        assert!((x - wx).abs() < 1e-6 && (y - wy).abs() < 1e-6, "{placed:?}");
        assert_eq!(source, want_source, "{placed:?}");
    }
    let crossed = placed
        .iter()
        .filter(|(_, _, _, heading)| *heading < 0.0)
        .count();
    // Those that crossed the road were turned around: (52, 1.6) → −2, (95, −1.8) → +2,
    // (101, 1.8) → −2; all keep their heights.
    assert_eq!(crossed, 3, "{placed:?}");
    assert!(codes
        .slots
        .iter()
        .all(|s| (s.slot_to_world.w_axis.z - 0.4).abs() < 1e-6));

    // More slots than the street holds at the smallest gap: refused, nothing printed.
    let out = Command::new(example())
        .args(["--lanes", "0", "--from", "0", "--to", "10"])
        .args(&paths)
        .output()
        .unwrap();
    assert!(!out.status.success() && out.stdout.is_empty());
    assert!(String::from_utf8_lossy(&out.stderr).contains("under --min-gap"));
}
