//! `colf-synth --resume`: continue an interrupted run in its own folder.
//!
//! A scene's `scene.json` is written last and atomically, so a scene whose `scene.json` exists
//! is complete. Each complete scene is checked against what these options would write — the
//! same preset, seed, split, size, cameras, look, engine, move — by sampling it again (cheap:
//! no rendering) and comparing every field of its `scene.json` but those counted from the
//! renders. A scene made with other options stops the run before anything is written, so a
//! resumed folder never mixes two runs. Incomplete scenes are removed and rendered again.

use super::{
    analytic_look, renders_manip, scene_dir_name, scene_doc, uorf, Engine, OutputLayout,
    SynthOptions,
};
use anyhow::{bail, Context, Result};
use rayon::prelude::*;
use serde_json::{json, Value};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// Fields of `scene.json` counted from the rendered images, not sampled: taken from the file
/// when it is compared. Per object: `visible_pixels`; per scene: the rest.
const RENDERED_SCENE_FIELDS: [&str; 3] = [
    "blender_lights",
    "uorf_mask_levels",
    "uorf_moved_mask_levels",
];

/// The scenes of `args` still to render in `args.out`, in order, after checking the complete
/// ones and removing the files of incomplete ones. Fails, having changed nothing, if the
/// folder holds scenes of another run.
pub fn pending_scenes(args: &SynthOptions) -> Result<Vec<u64>> {
    let out = args.out.as_path();
    let shown = out.display();
    if !out.exists() {
        return Ok((0..args.scenes).collect());
    }
    if !out.is_dir() {
        bail!("{shown}: exists and is not a folder");
    }
    let found = scan(out, args.layout)?;
    if let Some(&index) = found.started.iter().find(|&&i| i >= args.scenes) {
        bail!(
            "{shown}: holds scene {index}, beyond the {} scenes asked for: --resume continues \
             the same command (--force starts again)",
            args.scenes
        );
    }
    found
        .complete
        .par_iter()
        .try_for_each(|&index| check_scene(args, index))?;
    let mut pending = Vec::new();
    for index in 0..args.scenes {
        if found.complete.contains(&index) {
            continue;
        }
        if found.started.contains(&index) {
            remove_scene(out, args.layout, index)?;
        }
        pending.push(index);
    }
    Ok(pending)
}

/// What an output folder holds: scenes with any file, and scenes with their `scene.json`.
struct Found {
    started: BTreeSet<u64>,
    complete: BTreeSet<u64>,
}

/// Lists the scenes in `out`, refusing the files of the other layout.
fn scan(out: &Path, layout: OutputLayout) -> Result<Found> {
    let shown = out.display();
    let mut found = Found {
        started: BTreeSet::new(),
        complete: BTreeSet::new(),
    };
    let entries =
        std::fs::read_dir(out).with_context(|| format!("{shown}: cannot read the folder"))?;
    for entry in entries {
        let entry = entry.with_context(|| format!("{shown}: cannot read the folder"))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let colf_scene = colf_scene_of(name);
        let uorf_scene = uorf_scene_of(name);
        let (index, other_layout) = match (layout, colf_scene, uorf_scene) {
            (OutputLayout::Colf, Some(i), _) => (i, false),
            (OutputLayout::Uorf, _, Some(i)) => (i, false),
            (OutputLayout::Colf, None, Some(_)) => (0, true),
            (OutputLayout::Uorf, Some(_), None) => (0, true),
            _ => continue,
        };
        if other_layout {
            bail!(
                "{}: a file of the other --layout; --resume continues the same command",
                out.join(name).display()
            );
        }
        found.started.insert(index);
        let done = match layout {
            OutputLayout::Colf => out.join(name).join("scene.json").is_file(),
            OutputLayout::Uorf => name == format!("sc{index:04}_scene.json"),
        };
        if done {
            found.complete.insert(index);
        }
    }
    Ok(found)
}

/// `d` as a scene index, if it is all digits.
fn number(d: &str) -> Option<u64> {
    (!d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()))
        .then(|| d.parse::<u64>().ok())
        .flatten()
}

/// The scene index of a colf-layout scene folder, `scene_NNNNN`.
pub(super) fn colf_scene_of(name: &str) -> Option<u64> {
    name.strip_prefix("scene_").and_then(number)
}

/// The scene index of a uORF-layout file: `{i:05}_sc{s:04}_az{v:02}…`,
/// `sc{s:04}_scene.json` or `{s:03}_movement.txt`.
pub(super) fn uorf_scene_of(name: &str) -> Option<u64> {
    if let Some(rest) = name.strip_prefix("sc") {
        return rest.strip_suffix("_scene.json").and_then(number);
    }
    if let Some(d) = name.strip_suffix("_movement.txt") {
        return number(d);
    }
    let (_, after) = name.split_once("_sc")?;
    let (d, _) = after.split_once("_az")?;
    number(d)
}

/// Removes what an interrupted run wrote of scene `index`.
fn remove_scene(out: &Path, layout: OutputLayout, index: u64) -> Result<()> {
    let remove = |path: PathBuf| -> Result<()> {
        let removed = if path.is_dir() && !path.is_symlink() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        removed.with_context(|| format!("{}: cannot remove the unfinished scene", path.display()))
    };
    match layout {
        OutputLayout::Colf => remove(out.join(scene_dir_name(index))),
        OutputLayout::Uorf => {
            let entries = std::fs::read_dir(out)
                .with_context(|| format!("{}: cannot read the folder", out.display()))?;
            for entry in entries {
                let name = entry
                    .with_context(|| format!("{}: cannot read the folder", out.display()))?
                    .file_name();
                if name.to_str().and_then(uorf_scene_of) == Some(index) {
                    remove(out.join(name))?;
                }
            }
            Ok(())
        }
    }
}

/// Checks that complete scene `index` is the one these options make.
fn check_scene(args: &SynthOptions, index: u64) -> Result<()> {
    let path = match args.layout {
        OutputLayout::Colf => args.out.join(scene_dir_name(index)).join("scene.json"),
        OutputLayout::Uorf => args.out.join(format!("sc{index:04}_scene.json")),
    };
    let shown = path.display();
    let text = std::fs::read_to_string(&path).with_context(|| format!("{shown}: cannot read"))?;
    let written: Value =
        serde_json::from_str(&text).with_context(|| format!("{shown}: not valid JSON"))?;
    let expected = expected_doc(args, index, &written)?;
    if let Some(field) = first_difference(&expected, &written) {
        bail!(
            "{shown}: made by other options than these ({field} differs); --resume continues \
             the same command (--force starts again)"
        );
    }
    Ok(())
}

/// The `scene.json` these options write for scene `index`, with the fields counted from the
/// renders taken from `written`.
fn expected_doc(args: &SynthOptions, index: u64, written: &Value) -> Result<Value> {
    let mut sampled = args.sample(index)?;
    let extra = match &args.engine {
        Engine::Analytic => analytic_look(args, &mut sampled).1,
        Engine::Blender(b) => json!({ "engine": "blender", "samples": b.samples }),
    };
    let mut scene = sampled.scene.clone();
    if let Some(objects) = written["objects"].as_array() {
        if objects.len() == scene.objects.len() {
            for (object, w) in scene.objects.iter_mut().zip(objects) {
                if let Ok(pixels) = serde_json::from_value(w["visible_pixels"].clone()) {
                    object.visible_pixels = pixels;
                }
            }
        }
    }
    let mut doc = scene_doc(args, index, &scene, sampled.scene_seed, extra)?;
    for field in RENDERED_SCENE_FIELDS {
        if let Some(v) = written.get(field) {
            doc[field] = v.clone();
        }
    }
    if renders_manip(args) {
        doc["uorf_providing_bg_scene"] = json!(uorf::providing_scene(index, args.scenes));
    }
    Ok(doc)
}

/// The first top-level field in which two documents differ, if any: the options' own fields
/// first (a different seed also moves the cameras, and the seed is what to name).
fn first_difference(expected: &Value, written: &Value) -> Option<String> {
    const OPTIONS_FIRST: [&str; 10] = [
        "format",
        "preset",
        "split",
        "seed",
        "size",
        "engine",
        "samples",
        "look",
        "moved",
        "scene_seed",
    ];
    let (Some(e), Some(w)) = (expected.as_object(), written.as_object()) else {
        return (expected != written).then(|| "the document".to_string());
    };
    let rest: BTreeSet<&str> = e.keys().chain(w.keys()).map(String::as_str).collect();
    OPTIONS_FIRST
        .into_iter()
        .chain(rest)
        .find(|k| e.get(*k) != w.get(*k))
        .map(|k| format!("`{k}`"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{run, Preset, Progress, Split};

    fn options(out: &Path, scenes: u64, seed: u64, layout: OutputLayout) -> SynthOptions {
        SynthOptions {
            out: out.to_path_buf(),
            scenes,
            seed,
            size: 16,
            views: 2,
            preset: Preset::Clevr567,
            split: Split::Train,
            moved: None,
            engine: Engine::Analytic,
            layout,
            randomize_look: true,
            randomize_camera: false,
            replace: false,
            resume: false,
        }
    }

    /// Every file under `dir` with its bytes, by relative path.
    fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
        let mut all = Vec::new();
        let mut stack = vec![dir.to_path_buf()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    let bytes = std::fs::read(&p).unwrap();
                    all.push((p.strip_prefix(dir).unwrap().to_path_buf(), bytes));
                }
            }
        }
        all.sort();
        all
    }

    fn quiet(_: Progress) {}

    #[test]
    fn resuming_an_interrupted_run_gives_the_same_bytes() {
        for layout in [OutputLayout::Colf, OutputLayout::Uorf] {
            let dir = tempfile::tempdir().unwrap();
            let (whole, cut) = (dir.path().join("whole"), dir.path().join("cut"));
            run(&options(&whole, 4, 3, layout), &quiet).unwrap();
            run(&options(&cut, 4, 3, layout), &quiet).unwrap();
            // Interrupted: dataset.json not yet written, scene 1 half written, scene 3 not begun.
            std::fs::remove_file(cut.join("dataset.json")).unwrap();
            match layout {
                OutputLayout::Colf => {
                    std::fs::remove_file(cut.join("scene_00001/scene.json")).unwrap();
                    std::fs::remove_file(cut.join("scene_00001/view_001.png")).unwrap();
                    std::fs::remove_dir_all(cut.join("scene_00003")).unwrap();
                }
                OutputLayout::Uorf => {
                    std::fs::remove_file(cut.join("sc0001_scene.json")).unwrap();
                    std::fs::remove_file(cut.join("00003_sc0001_az01.png")).unwrap();
                    for (name, _) in files(&cut) {
                        if uorf_scene_of(name.to_str().unwrap()) == Some(3) {
                            std::fs::remove_file(cut.join(name)).unwrap();
                        }
                    }
                }
            }
            let mut resumed = options(&cut, 4, 3, layout);
            resumed.resume = true;
            assert_eq!(pending_scenes(&resumed).unwrap(), vec![1, 3]);
            run(&resumed, &quiet).unwrap();
            assert_eq!(files(&cut), files(&whole), "{layout:?}");
        }
    }

    #[test]
    fn scenes_of_other_options_are_refused_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("d");
        run(&options(&out, 3, 3, OutputLayout::Colf), &quiet).unwrap();
        std::fs::remove_file(out.join("scene_00002/scene.json")).unwrap();
        let before = files(&out);
        let refused = |o: SynthOptions| {
            let mut o = o;
            o.resume = true;
            let e = format!("{:#}", run(&o, &quiet).unwrap_err());
            assert_eq!(files(&out), before, "{e}");
            e
        };
        let e = refused(options(&out, 3, 4, OutputLayout::Colf));
        assert!(
            e.contains("scene_00000/scene.json") && e.contains("`seed`"),
            "{e}"
        );
        let mut no_look = options(&out, 3, 3, OutputLayout::Colf);
        no_look.randomize_look = false;
        assert!(refused(no_look).contains("differs"));
        let mut larger = options(&out, 3, 3, OutputLayout::Colf);
        larger.size = 24;
        assert!(refused(larger).contains("`size`"));
        let e = refused(options(&out, 2, 3, OutputLayout::Colf));
        assert!(e.contains("beyond the 2 scenes"), "{e}");
        let e = refused(options(&out, 3, 3, OutputLayout::Uorf));
        assert!(e.contains("other --layout"), "{e}");
    }

    #[test]
    fn uorf_names_give_their_scene() {
        assert_eq!(uorf_scene_of("00013_sc0003_az01.png"), Some(3));
        assert_eq!(uorf_scene_of("00013_sc0003_az01_mask_for_bg.png"), Some(3));
        assert_eq!(uorf_scene_of("sc0012_scene.json"), Some(12));
        assert_eq!(uorf_scene_of("007_movement.txt"), Some(7));
        assert_eq!(uorf_scene_of("dataset.json"), None);
        assert_eq!(uorf_scene_of("notes_sc_az.txt"), None);
    }
}
