//! Multi-view datasets on disk, for training and evaluation.
//!
//! Two layouts are read:
//! - **colf** (what `colf-synth` writes): `ROOT/<scene>/transforms.json` with its frames'
//!   images beside it and, optionally, masks `<stem>.mask.png` (8-bit grey: 0 = background,
//!   k = object k). Scene folders are every sub-folder holding a `transforms.json`, in name
//!   order; `ROOT` itself may be a single scene folder.
//! - **uORF** (flat): `{idx:05}_sc{scene:04}_az{view:02}.png` images, `…_RT.txt` camera-to-world
//!   in OpenCV axes (converted to our OpenGL axes), optional `…_mask.png`; intrinsics
//!   fx = 350/320·W, fy = 350/240·H, centred (uORF's `Projection`). Views of a scene are
//!   ordered by `az`. Mask grey levels (RGB masks are turned grey as PIL's `convert("L")`
//!   does) map to ids as in uORF's loader: in each view the second-smallest level is the
//!   background (id 0); every other level seen in the scene gets an id 1, 2, … in increasing
//!   grey order, the same in every view. Other files of the layout (`_azi_rot.txt`, uORF's
//!   scene-manipulation images and masks) are not read.
//!
//! Images are returned as **sRGB-encoded values in [0, 1]** (8-bit value / 255), exactly as
//! stored — not linear light: that is what the model trains on and what the metrics compare.
//! Scenes are listed when the dataset is opened and decoded one at a time by [`Dataset::load`].

use crate::camera::{Cameras, Frame};
use crate::image_io::{decode_labels, decode_rgb, RgbImage32};
use anyhow::{anyhow, bail, Context, Result};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The file layout of a dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    Colf,
    Uorf,
}

/// One view of a scene.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// The image file.
    pub path: PathBuf,
    /// sRGB values in [0, 1], row-major RGB.
    pub image: RgbImage32,
    /// Object ids per pixel (0 = background), row-major, when the dataset has masks.
    pub mask: Option<Vec<u8>>,
    /// The camera (OpenGL axes, camera-to-world).
    pub frame: Frame,
}

/// One scene: its views in order (view 0 is the input view of the uORF protocol).
#[derive(Clone, Debug, PartialEq)]
pub struct SceneData {
    pub name: String,
    pub views: Vec<View>,
    /// Whether mask ids are local to each view (object proposals, [`crate::proposals`]: the
    /// same object may have different ids in two views) rather than one per object of the scene.
    pub view_local_ids: bool,
}

#[derive(Clone, Debug)]
struct UorfView {
    image: PathBuf,
    rt: PathBuf,
    mask: Option<PathBuf>,
}

#[derive(Clone, Debug)]
enum Source {
    Colf(PathBuf),
    Uorf { scene: u32, views: Vec<UorfView> },
}

/// A dataset: the list of its scenes.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub root: PathBuf,
    pub layout: Layout,
    scenes: Vec<Source>,
    /// Whether [`Dataset::load`] reads mask files ([`Dataset::without_masks`] turns it off).
    read_masks: bool,
}

/// Parses a uORF image name `{idx}_sc{scene}_az{view}.png` into (idx, scene, view).
fn parse_uorf_name(name: &str) -> Option<(u32, u32, u32)> {
    let stem = name.strip_suffix(".png")?;
    let mut parts = stem.split('_');
    let (idx, sc, az) = (parts.next()?, parts.next()?, parts.next()?);
    if parts.next().is_some() {
        return None;
    }
    let number = |s: &str| -> Option<u32> {
        (!s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse().ok())
            .flatten()
    };
    Some((
        number(idx)?,
        number(sc.strip_prefix("sc")?)?,
        number(az.strip_prefix("az")?)?,
    ))
}

impl Dataset {
    /// Lists the scenes under `root` (see the module documentation for the layouts).
    pub fn open(root: impl AsRef<Path>) -> Result<Dataset> {
        let root = root.as_ref().to_path_buf();
        let shown = root.display().to_string();
        if !root.is_dir() {
            bail!("{shown}: not a folder");
        }
        if root.join("transforms.json").is_file() {
            return Ok(Dataset {
                scenes: vec![Source::Colf(root.clone())],
                root,
                layout: Layout::Colf,
                read_masks: true,
            });
        }
        let mut entries: Vec<(String, PathBuf)> = std::fs::read_dir(&root)
            .with_context(|| format!("{shown}: cannot list the folder"))?
            .map(|e| {
                let e = e.with_context(|| format!("{shown}: cannot list the folder"))?;
                Ok((e.file_name().to_string_lossy().into_owned(), e.path()))
            })
            .collect::<Result<_>>()?;
        entries.sort();
        let colf: Vec<Source> = entries
            .iter()
            .filter(|(_, p)| p.join("transforms.json").is_file())
            .map(|(_, p)| Source::Colf(p.clone()))
            .collect();
        if !colf.is_empty() {
            return Ok(Dataset {
                root,
                layout: Layout::Colf,
                scenes: colf,
                read_masks: true,
            });
        }
        let mut by_scene: BTreeMap<u32, BTreeMap<u32, UorfView>> = BTreeMap::new();
        for (name, path) in &entries {
            let Some((_, scene, az)) = parse_uorf_name(name) else {
                continue;
            };
            let stem = name.trim_end_matches(".png");
            let rt = root.join(format!("{stem}_RT.txt"));
            if !rt.is_file() {
                bail!("{}: camera file missing", rt.display());
            }
            let mask = root.join(format!("{stem}_mask.png"));
            let view = UorfView {
                image: path.clone(),
                rt,
                mask: mask.is_file().then_some(mask),
            };
            if by_scene
                .entry(scene)
                .or_default()
                .insert(az, view)
                .is_some()
            {
                bail!("{shown}: scene {scene} has two images of view az{az:02}");
            }
        }
        if by_scene.is_empty() {
            bail!(
                "{shown}: no scenes found (expected scene folders with transforms.json, or uORF \
                 files like 00000_sc0000_az00.png)"
            );
        }
        Ok(Dataset {
            root,
            layout: Layout::Uorf,
            read_masks: true,
            scenes: by_scene
                .into_iter()
                .map(|(scene, views)| Source::Uorf {
                    scene,
                    views: views.into_values().collect(),
                })
                .collect(),
        })
    }

    /// Number of scenes.
    pub fn len(&self) -> usize {
        self.scenes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.scenes.is_empty()
    }

    /// Name of scene `index`: its folder name (colf) or `scNNNN` (uORF).
    pub fn scene_name(&self, index: usize) -> String {
        match &self.scenes[index] {
            Source::Colf(dir) => dir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| dir.display().to_string()),
            Source::Uorf { scene, .. } => format!("sc{scene:04}"),
        }
    }

    /// The same dataset, loaded without ever opening a mask file (training without labels):
    /// every view's `mask` is None.
    pub fn without_masks(self) -> Dataset {
        Dataset {
            read_masks: false,
            ..self
        }
    }

    /// Reads and decodes scene `index` (panics if `index >= len()`).
    pub fn load(&self, index: usize) -> Result<SceneData> {
        let name = self.scene_name(index);
        let views = match &self.scenes[index] {
            Source::Colf(dir) => load_colf(dir, self.read_masks)?,
            Source::Uorf { views, .. } => load_uorf(views, self.read_masks)?,
        };
        Ok(SceneData {
            name,
            views,
            view_local_ids: false,
        })
    }
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))
}

fn check_size(path: &Path, (w, h): (u32, u32), frame: &Frame) -> Result<()> {
    let k = &frame.intrinsics;
    if (w, h) != (k.w, k.h) {
        bail!(
            "{}: image is {w}x{h} but its camera says {}x{}",
            path.display(),
            k.w,
            k.h
        );
    }
    Ok(())
}

fn load_colf(dir: &Path, read_masks: bool) -> Result<Vec<View>> {
    let transforms = dir.join("transforms.json");
    let cameras = Cameras::read(&transforms.to_string_lossy())?;
    cameras
        .frames
        .into_iter()
        .enumerate()
        .map(|(i, frame)| {
            let file = frame
                .file_path
                .clone()
                .ok_or_else(|| anyhow!("{}: frame {i} has no file_path", transforms.display()))?;
            let path = dir.join(&file);
            let shown = path.display().to_string();
            let image = decode_rgb(&read(&path)?, &shown)?;
            check_size(&path, (image.w, image.h), &frame)?;
            let stem = frame.stem().unwrap_or_default();
            let mask_path = path.with_file_name(format!("{stem}.mask.png"));
            let mask = if read_masks && mask_path.is_file() {
                let shown = mask_path.display().to_string();
                let (w, h, labels) = decode_labels(&read(&mask_path)?, &shown)?;
                check_size(&mask_path, (w, h), &frame)?;
                let ids = labels
                    .into_iter()
                    .map(|l| u8::try_from(l).map_err(|_| anyhow!("{shown}: mask id {l} > 255")))
                    .collect::<Result<Vec<u8>>>()?;
                Some(ids)
            } else {
                None
            };
            Ok(View {
                path,
                image,
                mask,
                frame,
            })
        })
        .collect()
}

/// Grey levels of a uORF mask, as PIL's `convert("L")` computes them for colour images.
pub fn uorf_mask_levels(bytes: &[u8], name: &str) -> Result<(u32, u32, Vec<u8>)> {
    crate::image_io::check_png_palette(bytes, name)?;
    let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png).map_err(|e| {
        anyhow!(
            "{name}: not a valid PNG image: {}",
            e.to_string().replace('\n', " ")
        )
    })?;
    let (w, h) = (img.width(), img.height());
    let levels = match img {
        image::DynamicImage::ImageLuma8(b) => b.into_raw(),
        other => other
            .to_rgb8()
            .pixels()
            .map(|p| {
                let [r, g, b] = p.0.map(|c| c as u32);
                ((r * 19595 + g * 38470 + b * 7471 + 0x8000) >> 16) as u8
            })
            .collect(),
    };
    Ok((w, h, levels))
}

/// uORF's background level of one view: the second-smallest grey level (the only one if
/// there is only one).
fn uorf_background(levels: &[u8]) -> u8 {
    let distinct: BTreeSet<u8> = levels.iter().copied().collect();
    let mut it = distinct.into_iter();
    let first = it.next().unwrap_or(0);
    it.next().unwrap_or(first)
}

fn load_uorf(views: &[UorfView], read_masks: bool) -> Result<Vec<View>> {
    let mut out = Vec::with_capacity(views.len());
    let mut masks: Vec<Option<(Vec<u8>, u8)>> = Vec::with_capacity(views.len());
    for v in views {
        let shown = v.image.display().to_string();
        let image = decode_rgb(&read(&v.image)?, &shown)?;
        let rt_text =
            String::from_utf8(read(&v.rt)?).map_err(|_| anyhow!("{}: not text", v.rt.display()))?;
        let camera_to_world = Cameras::uorf_pose_from_text(&rt_text, &v.rt.display().to_string())?;
        let frame = Frame {
            file_path: v
                .image
                .file_name()
                .map(|n| n.to_string_lossy().into_owned()),
            intrinsics: Cameras::uorf_intrinsics(image.w, image.h),
            camera_to_world,
        };
        masks.push(match v.mask.as_ref().filter(|_| read_masks) {
            Some(path) => {
                let (w, h, levels) = uorf_mask_levels(&read(path)?, &path.display().to_string())?;
                check_size(path, (w, h), &frame)?;
                let bg = uorf_background(&levels);
                Some((levels, bg))
            }
            None => None,
        });
        out.push(View {
            path: v.image.clone(),
            image,
            mask: None,
            frame,
        });
    }
    // One id per non-background level over the whole scene, in increasing grey order.
    let objects: BTreeSet<u8> = masks
        .iter()
        .flatten()
        .flat_map(|(levels, bg)| levels.iter().copied().filter(move |l| l != bg))
        .collect();
    let id_of: BTreeMap<u8, u8> = objects
        .into_iter()
        .enumerate()
        .map(|(i, level)| (level, (i + 1) as u8))
        .collect();
    for (view, mask) in out.iter_mut().zip(masks) {
        view.mask = mask.map(|(levels, bg)| {
            levels
                .into_iter()
                .map(|l| if l == bg { 0 } else { id_of[&l] })
                .collect()
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uorf_names_parse() {
        assert_eq!(parse_uorf_name("00012_sc0003_az01.png"), Some((12, 3, 1)));
        assert_eq!(parse_uorf_name("00012_sc0003_az01_mask.png"), None);
        assert_eq!(parse_uorf_name("00012_sc0003_az01_RT.txt"), None);
        assert_eq!(parse_uorf_name("x_sc0003_az01.png"), None);
        assert_eq!(parse_uorf_name("00012_scene3_az01.png"), None);
    }

    #[test]
    fn uorf_background_is_the_second_smallest_level() {
        assert_eq!(uorf_background(&[200, 10, 64, 64, 10, 130]), 64);
        assert_eq!(uorf_background(&[7, 7]), 7);
    }

    #[test]
    fn pil_grey_conversion() {
        let mut png = Vec::new();
        use image::ImageEncoder;
        image::codecs::png::PngEncoder::new(&mut png)
            .write_image(
                &[255, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255, 255],
                4,
                1,
                image::ExtendedColorType::Rgb8,
            )
            .unwrap();
        let (_, _, l) = uorf_mask_levels(&png, "m.png").unwrap();
        // PIL: L = R·299/1000 + G·587/1000 + B·114/1000, rounded.
        assert_eq!(l, vec![76, 150, 29, 255]);
    }

    #[test]
    fn empty_or_missing_folders_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let msg = format!("{:#}", Dataset::open(dir.path()).unwrap_err());
        assert!(msg.contains("no scenes found"), "{msg}");
        let msg = format!("{:#}", Dataset::open(dir.path().join("nope")).unwrap_err());
        assert!(msg.contains("not a folder"), "{msg}");
        std::fs::write(dir.path().join("00000_sc0000_az00.png"), b"x").unwrap();
        let msg = format!("{:#}", Dataset::open(dir.path()).unwrap_err());
        assert!(msg.contains("_RT.txt: camera file missing"), "{msg}");
    }
}
