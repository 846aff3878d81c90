//! Image and segmentation metrics, defined exactly as uORF reports them (and as `colf-eval`
//! prints them):
//!
//! - [`psnr`]: over all RGB values in [0, 1] (8-bit value / 255), data range 1:
//!   `10 log10(1 / MSE)`; `+inf` for identical images.
//! - [`ssim`]: scikit-image's `structural_similarity(..., gaussian_weights=True, sigma=1.5,
//!   use_sample_covariance=False, data_range=1.0, channel_axis=-1)`: an 11×11 Gaussian window
//!   (σ = 1.5, truncated at 3.5 σ → radius 5), k1 = 0.01, k2 = 0.03, the SSIM map averaged over
//!   the valid region only (5 pixels cropped from every border), then over channels.
//! - [`region_psnr`]: [`psnr`] over a region's pixels and over the rest.
//! - [`ari`]: scikit-learn's `adjusted_rand_score`, from the contingency table with exact
//!   integer pair counts.
//! - [`fg_ari`]: ARI over the pixels whose ground-truth label is not 0 (the background).
//!
//! Everything is computed in `f64`; no metric is NaN for valid input (constant images and
//! single-cluster masks included).

use anyhow::{bail, Result};
use serde::Serialize;
use std::collections::HashMap;

/// SSIM Gaussian window standard deviation, in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM window radius: scikit-image's `int(3.5 * sigma + 0.5)` (scipy's truncation), so the
/// window is 11×11.
pub const SSIM_RADIUS: usize = 5;
/// SSIM stabiliser constants (times the data range, 1).
pub const SSIM_K1: f64 = 0.01;
pub const SSIM_K2: f64 = 0.03;

/// Checks two value arrays for a metric: equal length, not empty, finite.
fn check_pair(pred: &[f32], gt: &[f32]) -> Result<()> {
    if pred.len() != gt.len() {
        bail!(
            "the images have {} and {} values; they must be the same size",
            pred.len(),
            gt.len()
        );
    }
    if pred.is_empty() {
        bail!("the images are empty");
    }
    if pred.iter().chain(gt).any(|v| !v.is_finite()) {
        bail!("the images contain a non-finite value");
    }
    Ok(())
}

/// Mean squared error between two equally long value arrays.
pub fn mse(pred: &[f32], gt: &[f32]) -> Result<f64> {
    check_pair(pred, gt)?;
    Ok(squared_error(pred, gt) / pred.len() as f64)
}

/// Sum of squared differences, in f64.
fn squared_error(pred: &[f32], gt: &[f32]) -> f64 {
    pred.iter()
        .zip(gt)
        .map(|(&a, &b)| {
            let d = a as f64 - b as f64;
            d * d
        })
        .sum()
}

/// Peak signal-to-noise ratio in dB for values in [0, 1] (data range 1), as scikit-image's
/// `peak_signal_noise_ratio(gt, pred, data_range=1)`. Identical inputs give `f64::INFINITY`
/// (`colf-eval` prints it as JSON `null`, see [`ImageScores`]).
pub fn psnr(pred: &[f32], gt: &[f32]) -> Result<f64> {
    Ok(psnr_from_mse(mse(pred, gt)?))
}

/// The PSNR of [`psnr`] over two regions of an image: the pixels where `inside` holds, and the
/// rest (`pred` and `gt` hold `inside.len()` pixels of equally many channels). `None` for a
/// region without pixels. `colf-eval --data` splits the novel views' PSNR this way by the
/// ground-truth masks (`object_psnr`, `background_psnr`).
pub fn region_psnr(
    pred: &[f32],
    gt: &[f32],
    inside: &[bool],
) -> Result<(Option<f64>, Option<f64>)> {
    check_pair(pred, gt)?;
    if inside.is_empty() || !pred.len().is_multiple_of(inside.len()) {
        bail!(
            "the images have {} values, not a whole number of channels for {} pixels",
            pred.len(),
            inside.len()
        );
    }
    let channels = pred.len() / inside.len();
    // [sum of squared errors, values] inside and outside.
    let mut sums = [[0.0f64; 2]; 2];
    for ((a, b), &is_in) in pred
        .chunks_exact(channels)
        .zip(gt.chunks_exact(channels))
        .zip(inside)
    {
        let sum = &mut sums[usize::from(!is_in)];
        sum[0] += squared_error(a, b);
        sum[1] += channels as f64;
    }
    let region = |[squared, n]: [f64; 2]| (n > 0.0).then(|| psnr_from_mse(squared / n));
    Ok((region(sums[0]), region(sums[1])))
}

/// PSNR in dB of a mean squared error for values in [0, 1]: `10 log10(1 / mse)`, `+inf` at 0.
/// Training logs floor the error first (`mse.max(1e-12)`) so a perfect batch logs 120 dB.
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (1.0 / mse).log10()
    }
}

/// Normalised 1-D Gaussian taps `exp(-x² / 2σ²)` for x in -radius..=radius (scipy's
/// `_gaussian_kernel1d`).
fn gaussian_taps() -> [f64; 2 * SSIM_RADIUS + 1] {
    let mut taps = [0.0; 2 * SSIM_RADIUS + 1];
    for (i, t) in taps.iter_mut().enumerate() {
        let x = i as f64 - SSIM_RADIUS as f64;
        *t = (-0.5 * x * x / (SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let sum: f64 = taps.iter().sum();
    taps.iter_mut().for_each(|t| *t /= sum);
    taps
}

/// Mean SSIM of two images of `width × height` pixels with `channels` interleaved values per
/// pixel (row-major), values in [0, 1]; see the module docs for the exact definition. Each
/// side must be at least 11 pixels (the window), as scikit-image requires.
///
/// Only the valid region is filtered: a window centred there never reaches the border, so the
/// border mode of scikit-image's filter (reflect) does not enter the result.
pub fn ssim(pred: &[f32], gt: &[f32], width: usize, height: usize, channels: usize) -> Result<f64> {
    check_pair(pred, gt)?;
    if channels == 0 || pred.len() != width * height * channels {
        bail!(
            "{} values do not make a {width}x{height} image with {channels} channels",
            pred.len()
        );
    }
    let win = 2 * SSIM_RADIUS + 1;
    if width < win || height < win {
        bail!("{width}x{height} is smaller than the {win}x{win} SSIM window");
    }
    let taps = gaussian_taps();
    let c1 = SSIM_K1 * SSIM_K1;
    let c2 = SSIM_K2 * SSIM_K2;
    let (valid_w, valid_h) = (width - 2 * SSIM_RADIUS, height - 2 * SSIM_RADIUS);

    let mut total = 0.0;
    for c in 0..channels {
        let x: Vec<f64> = (0..width * height)
            .map(|p| pred[p * channels + c] as f64)
            .collect();
        let y: Vec<f64> = (0..width * height)
            .map(|p| gt[p * channels + c] as f64)
            .collect();
        // Horizontal pass over every row, valid columns only: five moments per pixel
        // (x, y, x², y², xy), as scikit-image filters the five images.
        let mut rows = vec![[0.0f64; 5]; height * valid_w];
        for r in 0..height {
            for vc in 0..valid_w {
                let mut acc = [0.0; 5];
                for (k, &t) in taps.iter().enumerate() {
                    let i = r * width + vc + k;
                    let (a, b) = (x[i], y[i]);
                    acc[0] += t * a;
                    acc[1] += t * b;
                    acc[2] += t * a * a;
                    acc[3] += t * b * b;
                    acc[4] += t * a * b;
                }
                rows[r * valid_w + vc] = acc;
            }
        }
        // Vertical pass at the valid rows, then the SSIM map, summed.
        let mut sum = 0.0;
        for vr in 0..valid_h {
            for vc in 0..valid_w {
                let mut m = [0.0; 5];
                for (k, &t) in taps.iter().enumerate() {
                    let row = &rows[(vr + k) * valid_w + vc];
                    for (mi, ri) in m.iter_mut().zip(row) {
                        *mi += t * ri;
                    }
                }
                let [ux, uy, uxx, uyy, uxy] = m;
                let vx = uxx - ux * ux;
                let vy = uyy - uy * uy;
                let vxy = uxy - ux * uy;
                let num = (2.0 * ux * uy + c1) * (2.0 * vxy + c2);
                let den = (ux * ux + uy * uy + c1) * (vx + vy + c2);
                sum += num / den;
            }
        }
        total += sum / (valid_w * valid_h) as f64;
    }
    Ok(total / channels as f64)
}

/// Adjusted Rand index of two labelings of the same pixels, exactly as scikit-learn's
/// `adjusted_rand_score(gt, pred)` (symmetric in its arguments). Identical partitions (up to a
/// renaming of the labels) give 1.0, including the cases where the index is otherwise 0/0:
/// both labelings one cluster, both all singletons, or no pixels at all.
pub fn ari(pred: &[u32], gt: &[u32]) -> Result<f64> {
    if pred.len() != gt.len() {
        bail!(
            "the masks have {} and {} pixels; they must be the same size",
            pred.len(),
            gt.len()
        );
    }
    let mut table: HashMap<(u32, u32), u64> = HashMap::new();
    let mut gt_sizes: HashMap<u32, u64> = HashMap::new();
    let mut pred_sizes: HashMap<u32, u64> = HashMap::new();
    for (&p, &g) in pred.iter().zip(gt) {
        *table.entry((g, p)).or_default() += 1;
        *gt_sizes.entry(g).or_default() += 1;
        *pred_sizes.entry(p).or_default() += 1;
    }
    // Ordered pair counts as scikit-learn's `pair_confusion_matrix`, in i128: products of pair
    // counts reach n⁴ (≈1e24 for a 1-megapixel image), past u64.
    let square_sum = |counts: &mut dyn Iterator<Item = u64>| -> i128 {
        counts.map(|c| c as i128 * c as i128).sum()
    };
    let n = pred.len() as i128;
    let sum_sq = square_sum(&mut table.values().copied());
    let gt_sq = square_sum(&mut gt_sizes.values().copied());
    let pred_sq = square_sum(&mut pred_sizes.values().copied());
    let tp = sum_sq - n; // same cluster in both
    let fp = pred_sq - sum_sq; // same cluster in pred only
    let fn_ = gt_sq - sum_sq; // same cluster in gt only
    let tn = n * n - fp - fn_ - sum_sq; // different clusters in both
    if fn_ == 0 && fp == 0 {
        return Ok(1.0);
    }
    // Exact integers while they fit (always, below ~4e9 pixels), f64 beyond.
    let exact = || -> Option<(i128, i128)> {
        let num = tp.checked_mul(tn)?.checked_sub(fn_.checked_mul(fp)?)?;
        let den = (tp + fn_)
            .checked_mul(fn_ + tn)?
            .checked_add((tp + fp).checked_mul(fp + tn)?)?;
        Some((num, den))
    };
    Ok(match exact() {
        Some((num, den)) => 2.0 * num as f64 / den as f64,
        None => {
            let (tp, fp, fn_, tn) = (tp as f64, fp as f64, fn_ as f64, tn as f64);
            2.0 * (tp * tn - fn_ * fp) / ((tp + fn_) * (fn_ + tn) + (tp + fp) * (fp + tn))
        }
    })
}

/// Foreground ARI: [`ari`] over the pixels whose ground-truth label is not 0. `None` when the
/// ground truth has no foreground pixel (the score is undefined there).
pub fn fg_ari(pred: &[u32], gt: &[u32]) -> Result<Option<f64>> {
    if pred.len() != gt.len() {
        bail!(
            "the masks have {} and {} pixels; they must be the same size",
            pred.len(),
            gt.len()
        );
    }
    let (fg_pred, fg_gt): (Vec<u32>, Vec<u32>) = pred
        .iter()
        .zip(gt)
        .filter(|(_, &g)| g != 0)
        .map(|(&p, &g)| (p, g))
        .unzip();
    if fg_gt.is_empty() {
        return Ok(None);
    }
    ari(&fg_pred, &fg_gt).map(Some)
}

/// Mean and population standard deviation (divisor n, numpy's `np.std` default) of the finite
/// values; `None` values (a score undefined for a scene) and non-finite ones (an infinite
/// PSNR) are left out. `(None, None)` when nothing is left. `colf-eval --data` reports a
/// score's mean and spread over scenes, and over the runs of `--seeds`, with it.
pub fn mean_std(values: impl IntoIterator<Item = Option<f64>>) -> (Option<f64>, Option<f64>) {
    let v: Vec<f64> = values
        .into_iter()
        .flatten()
        .filter(|x| x.is_finite())
        .collect();
    if v.is_empty() {
        return (None, None);
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    (Some(mean), Some(var.sqrt()))
}

/// The image metrics of `colf-eval images`. JSON: `{"psnr": dB or null, "ssim": …}`; `psnr`
/// is `null` exactly when the images are identical (PSNR = +inf, which JSON cannot hold; no cap
/// is used because a cap would collide with real values on large images).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ImageScores {
    #[serde(serialize_with = "finite_or_null")]
    pub psnr: f64,
    pub ssim: f64,
}

impl ImageScores {
    /// Both metrics of two RGB images of `width × height` pixels, values in [0, 1].
    pub fn compute(pred: &[f32], gt: &[f32], width: usize, height: usize) -> Result<Self> {
        Ok(Self {
            psnr: psnr(pred, gt)?,
            ssim: ssim(pred, gt, width, height, 3)?,
        })
    }
}

/// The mask metrics of `colf-eval masks`. JSON: `{"ari": …, "fg_ari": … or null}`; `fg_ari` is
/// `null` when the ground truth has no foreground pixel.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MaskScores {
    pub ari: f64,
    pub fg_ari: Option<f64>,
}

impl MaskScores {
    /// Both metrics of two labelings of the same pixels; ground-truth label 0 is background.
    pub fn compute(pred: &[u32], gt: &[u32]) -> Result<Self> {
        Ok(Self {
            ari: ari(pred, gt)?,
            fg_ari: fg_ari(pred, gt)?,
        })
    }
}

/// Serialises a finite number as itself and ±inf or NaN as `null`.
fn finite_or_null<S: serde::Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
    if v.is_finite() {
        s.serialize_f64(*v)
    } else {
        s.serialize_none()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) {
        assert!((a - b).abs() <= tol, "{a} vs {b}");
    }

    #[test]
    fn psnr_of_a_known_mse() {
        // Every value off by 0.1 → MSE 0.01 → 20 dB.
        let gt = vec![0.5f32; 300];
        let pred: Vec<f32> = gt.iter().map(|v| v + 0.1).collect();
        close(psnr(&pred, &gt).unwrap(), 20.0, 1e-5);
        // One value in 100 off by 1 → MSE 0.01.
        let mut pred = vec![0.0f32; 100];
        pred[3] = 1.0;
        close(psnr(&pred, &[0.0; 100]).unwrap(), 20.0, 1e-12);
        assert_eq!(psnr(&gt, &gt).unwrap(), f64::INFINITY);
    }

    #[test]
    fn region_psnr_splits_the_error() {
        // Two RGB pixels: the first (inside) off by 0.1 in every channel, the second by 0.01.
        let gt = [0.5f32; 6];
        let pred = [0.6f32, 0.6, 0.6, 0.51, 0.51, 0.51];
        let (inside, outside) = region_psnr(&pred, &gt, &[true, false]).unwrap();
        close(inside.unwrap(), 20.0, 1e-5);
        close(outside.unwrap(), 40.0, 1e-4);
        // A region without pixels has no PSNR; the whole image is the other region.
        let (none, all) = region_psnr(&pred, &gt, &[false, false]).unwrap();
        assert_eq!(none, None);
        close(all.unwrap(), psnr(&pred, &gt).unwrap(), 1e-12);
        assert_eq!(
            region_psnr(&gt, &gt, &[true, false]).unwrap().0,
            Some(f64::INFINITY)
        );
        // Sizes that do not match are refused.
        assert!(region_psnr(&pred, &gt, &[true; 4]).is_err());
        assert!(region_psnr(&pred, &gt, &[]).is_err());
        assert!(region_psnr(&pred[..3], &gt, &[true]).is_err());
    }

    #[test]
    fn psnr_refuses_bad_input() {
        assert!(psnr(&[0.0; 3], &[0.0; 6]).is_err());
        assert!(psnr(&[], &[]).is_err());
        assert!(psnr(&[f32::NAN], &[0.0]).is_err());
    }

    #[test]
    fn gaussian_window_matches_scipy() {
        let taps = gaussian_taps();
        close(taps.iter().sum(), 1.0, 1e-15);
        // scipy.ndimage._filters._gaussian_kernel1d(1.5, 0, 5)[5] and [0].
        close(taps[5], 0.26601172486179436, 1e-15);
        close(taps[0], 0.00102838008447911, 1e-15);
    }

    /// Pseudo-random 8-bit values / 255 (a multiplicative hash of index and seed).
    fn pattern(w: usize, h: usize, seed: u32) -> Vec<f32> {
        (0..w * h * 3)
            .map(|i| {
                let mut x = (i as u32 ^ seed.wrapping_mul(0x9E37_79B9)).wrapping_mul(2654435761);
                x ^= x >> 15;
                x = x.wrapping_mul(2246822519);
                (x >> 24) as f32 / 255.0
            })
            .collect()
    }

    #[test]
    fn ssim_of_identical_images_is_one_and_constant_images_are_finite() {
        let img = pattern(16, 12, 1);
        close(ssim(&img, &img, 16, 12, 3).unwrap(), 1.0, 1e-12);
        let black = vec![0.0f32; 11 * 11 * 3];
        let white = vec![1.0f32; 11 * 11 * 3];
        close(ssim(&black, &black, 11, 11, 3).unwrap(), 1.0, 1e-12);
        // Constant images: variances 0, SSIM = C1 / (1 + C1) from the luminance term alone.
        let c1 = SSIM_K1 * SSIM_K1;
        close(
            ssim(&black, &white, 11, 11, 3).unwrap(),
            c1 / (1.0 + c1),
            1e-12,
        );
    }

    #[test]
    fn ssim_is_symmetric_and_below_one_for_different_images() {
        let (a, b) = (pattern(20, 15, 1), pattern(20, 15, 99));
        let s = ssim(&a, &b, 20, 15, 3).unwrap();
        close(s, ssim(&b, &a, 20, 15, 3).unwrap(), 1e-12);
        assert!(s < 0.5 && s > -1.0, "{s}");
    }

    #[test]
    fn ssim_refuses_images_smaller_than_the_window() {
        let img = vec![0.5f32; 10 * 20 * 3];
        let msg = format!("{:#}", ssim(&img, &img, 10, 20, 3).unwrap_err());
        assert!(msg.contains("11x11"), "{msg}");
        assert!(ssim(&img, &img, 20, 20, 3).is_err(), "wrong size accepted");
    }

    #[test]
    fn ari_is_invariant_to_renaming_labels() {
        let gt = [0, 0, 1, 1, 2, 2, 2, 5];
        let renamed = [7, 7, 3, 3, 0, 0, 0, 1];
        assert_eq!(ari(&renamed, &gt).unwrap(), 1.0);
    }

    #[test]
    fn ari_matches_hand_computed_values() {
        // Contingency {2, 1, 1}: Σ C(nij,2) = 1, rows Σ = 1, columns Σ = 2, C(4,2) = 6:
        // (1 - 1·2/6) / ((1 + 2)/2 - 1·2/6) = 4/7 (scikit-learn's doc example: 0.57).
        close(ari(&[0, 0, 1, 1], &[0, 0, 1, 2]).unwrap(), 4.0 / 7.0, 1e-15);
        close(ari(&[0, 0, 1, 2], &[0, 0, 1, 1]).unwrap(), 4.0 / 7.0, 1e-15);
        // (2 - 6·3/15) / ((6 + 3)/2 - 6·3/15) = 0.8 / 3.3.
        close(
            ari(&[0, 0, 1, 1, 2, 2], &[0, 0, 0, 1, 1, 1]).unwrap(),
            0.8 / 3.3,
            1e-15,
        );
        // Worse than chance: scikit-learn gives -0.5.
        close(ari(&[0, 1, 0, 1], &[0, 0, 1, 1]).unwrap(), -0.5, 1e-15);
    }

    #[test]
    fn ari_special_cases_are_one_not_nan() {
        assert_eq!(ari(&[3; 10], &[4; 10]).unwrap(), 1.0);
        assert_eq!(ari(&[0, 1, 2, 3], &[9, 8, 7, 6]).unwrap(), 1.0);
        assert_eq!(ari(&[], &[]).unwrap(), 1.0);
        // One cluster against all singletons: 0, as scikit-learn.
        assert_eq!(ari(&[0, 0, 0, 0], &[0, 1, 2, 3]).unwrap(), 0.0);
        assert!(ari(&[0, 1], &[0]).is_err());
    }

    #[test]
    fn ari_on_a_megapixel_does_not_overflow() {
        let n = 1 << 20;
        let gt: Vec<u32> = (0..n).map(|i| (i / 1000) as u32 % 7).collect();
        let pred: Vec<u32> = (0..n).map(|i| (i / 1000) as u32 % 7).collect();
        assert_eq!(ari(&pred, &gt).unwrap(), 1.0);
        let shifted: Vec<u32> = (0..n).map(|i| ((i + 300) / 1000) as u32 % 7).collect();
        let score = ari(&shifted, &gt).unwrap();
        assert!(score > 0.4 && score < 1.0, "{score}");
    }

    #[test]
    fn fg_ari_ignores_background_pixels() {
        // Prediction splits the background but segments the two objects perfectly.
        let gt = [0, 0, 0, 1, 1, 2, 2];
        let pred = [5, 6, 7, 1, 1, 2, 2];
        assert_eq!(fg_ari(&pred, &gt).unwrap(), Some(1.0));
        assert!(ari(&pred, &gt).unwrap() < 1.0);
        assert_eq!(fg_ari(&[1, 2], &[0, 0]).unwrap(), None);
    }

    /// A lone object scores all or nothing (scikit-learn agrees): 1 when one label draws it,
    /// 0 when a single edge pixel of it goes to another label, as when most of it does.
    #[test]
    fn fg_ari_of_a_lone_object_is_all_or_nothing() {
        let gt = [0, 0, 3, 3, 3, 3, 3, 3, 3, 3, 3, 3];
        let whole = [0, 1, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4];
        let one_edge_pixel_lost = [0, 0, 0, 4, 4, 4, 4, 4, 4, 4, 4, 4];
        let half = [0, 0, 4, 4, 4, 4, 4, 0, 0, 0, 0, 0];
        assert_eq!(fg_ari(&whole, &gt).unwrap(), Some(1.0));
        assert_eq!(fg_ari(&one_edge_pixel_lost, &gt).unwrap(), Some(0.0));
        assert_eq!(fg_ari(&half, &gt).unwrap(), Some(0.0));
    }

    #[test]
    fn scores_serialise_infinite_psnr_and_missing_fg_ari_as_null() {
        let s = ImageScores {
            psnr: f64::INFINITY,
            ssim: 1.0,
        };
        assert_eq!(
            serde_json::to_string(&s).unwrap(),
            r#"{"psnr":null,"ssim":1.0}"#
        );
        let m = MaskScores {
            ari: 0.5,
            fg_ari: None,
        };
        assert_eq!(
            serde_json::to_string(&m).unwrap(),
            r#"{"ari":0.5,"fg_ari":null}"#
        );
    }

    #[test]
    fn mean_std_is_the_population_spread_of_the_defined_values() {
        // numpy: np.mean([2, 4, 4, 4, 5, 5, 7, 9]) = 5, np.std(...) = 2.
        let v = [2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0].map(Some);
        assert_eq!(mean_std(v), (Some(5.0), Some(2.0)));
        // Undefined (None) and infinite values are left out, not counted as 0.
        let (m, s) = mean_std([
            Some(1.0),
            None,
            Some(f64::INFINITY),
            Some(3.0),
            Some(f64::NAN),
        ]);
        assert_eq!((m, s), (Some(2.0), Some(1.0)));
        // One value: no spread; none: no mean.
        assert_eq!(mean_std([Some(0.25)]), (Some(0.25), Some(0.0)));
        assert_eq!(mean_std([None, Some(f64::INFINITY)]), (None, None));
        assert_eq!(mean_std(std::iter::empty()), (None, None));
        // Three trials as SlotLifter reports them: 0.1 / sqrt(1.5) for {0.8, 0.9, 1.0}.
        let (m, s) = mean_std([0.8, 0.9, 1.0].map(Some));
        close(m.unwrap(), 0.9, 1e-15);
        close(s.unwrap(), (0.02f64 / 3.0).sqrt(), 1e-14);
    }
}
