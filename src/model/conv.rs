//! 3×3 convolutions on channels-last images as im2col + one fused dense layer.
//!
//! Why: candle's `conv2d` backward was the largest single cost of a training step (measured in
//! `docs/speed.md`, "Why the hot paths look as they do"). Unfolding the 3×3 neighbourhoods into
//! rows (`im2col`, whose backward `col2im` adds them back) turns a convolution into one gemm with
//! the fast backward of [`super::fused::dense`]. Keeping the encoder's activations channels-last
//! ([B, H, W, C]) makes each unfolded tap a contiguous run of C floats, and the final
//! [B, H, W, F] feature map is already the token layout slot attention wants.
//!
//! The weights keep candle's conv layout and names ([C_out, C_in, 3, 3] + [C_out]), so model
//! files are unchanged; the function is the same cross-correlation with zero padding 1.

use super::fused::{dense, Activation};
use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// y = act(conv3×3(x) + b) with zero padding 1: x [B, H, W, C_in] → [B, H', W', C_out],
/// H' = (H − 1) / stride + 1; `weight` [C_out, C_in, 3, 3], `bias` [C_out].
pub fn conv3x3(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    stride: usize,
    act: Activation,
) -> Result<Tensor> {
    let (b, h, w, c) = x.dims4()?;
    let (c_out, c_in, kh, kw) = weight.dims4()?;
    if c_in != c || kh != 3 || kw != 3 || stride == 0 {
        candle_core::bail!(
            "conv3x3: input with {c} channels, weight {:?}, stride {stride}",
            weight.dims()
        );
    }
    let (h_out, w_out) = ((h - 1) / stride + 1, (w - 1) / stride + 1);
    let cols = x.contiguous()?.apply_op1(Im2Col { stride })?; // [B·H'·W', 9·C]
                                                              // Columns are ordered (ky, kx, c): the matching weight matrix is [9·C_in, C_out].
    let matrix = weight
        .permute((0, 2, 3, 1))?
        .contiguous()?
        .reshape((c_out, 9 * c_in))?
        .t()?;
    dense(&cols, &matrix, bias, act)?.reshape((b, h_out, w_out, c_out))
}

/// Unfolds every 3×3 neighbourhood (zero padding 1) of a contiguous [B, H, W, C] image.
struct Im2Col {
    stride: usize,
}

fn out_size(n: usize, stride: usize) -> usize {
    (n - 1) / stride + 1
}

/// The contiguous f32 values of a custom op's input.
fn contiguous_f32<'a>(storage: &'a CpuStorage, layout: &Layout, op: &str) -> Result<&'a [f32]> {
    match (layout.contiguous_offsets(), storage) {
        (Some((start, end)), CpuStorage::F32(data)) => Ok(&data[start..end]),
        _ => candle_core::bail!("{op}: input must be contiguous f32"),
    }
}

/// Calls `f(tap, pixel)` for each of the 9 taps (ky·3 + kx) of output position (oy, ox) that
/// falls inside an h×w image (zero padding 1, `stride`), with the tap's pixel index y·w + x.
fn for_each_tap(
    (oy, ox): (usize, usize),
    stride: usize,
    (h, w): (usize, usize),
    mut f: impl FnMut(usize, usize),
) {
    for ky in 0..3 {
        let Some(iy) = (oy * stride + ky).checked_sub(1).filter(|&y| y < h) else {
            continue;
        };
        for kx in 0..3 {
            let Some(ix) = (ox * stride + kx).checked_sub(1).filter(|&x| x < w) else {
                continue;
            };
            f(ky * 3 + kx, iy * w + ix);
        }
    }
}

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "colf-im2col"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = contiguous_f32(storage, layout, "im2col")?;
        let &[b, h, w, c] = layout.dims() else {
            candle_core::bail!("im2col: input must be [B, H, W, C]");
        };
        let s = self.stride;
        let (ho, wo) = (out_size(h, s), out_size(w, s));
        let row = 9 * c;
        let mut cols = vec![0f32; b * ho * wo * row];
        cols.par_chunks_mut(wo * row)
            .enumerate()
            .for_each(|(line, out)| {
                let (bi, oy) = (line / ho, line % ho);
                let image = &x[bi * h * w * c..(bi + 1) * h * w * c];
                for ox in 0..wo {
                    for_each_tap((oy, ox), s, (h, w), |tap, pixel| {
                        let dst = ox * row + tap * c;
                        out[dst..dst + c].copy_from_slice(&image[pixel * c..(pixel + 1) * c]);
                    });
                }
            });
        Ok((CpuStorage::F32(cols), Shape::from((b * ho * wo, row))))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let grad = grad_res.contiguous()?.apply_op1_no_bwd(&Col2Im {
            stride: self.stride,
            input: arg.dims4()?,
        })?;
        Ok(Some(grad))
    }
}

/// The adjoint of [`Im2Col`]: adds each unfolded tap back to its pixel.
struct Col2Im {
    stride: usize,
    input: (usize, usize, usize, usize),
}

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "colf-col2im"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let cols = contiguous_f32(storage, layout, "col2im")?;
        let (b, h, w, c) = self.input;
        let s = self.stride;
        let (ho, wo) = (out_size(h, s), out_size(w, s));
        let row = 9 * c;
        if cols.len() != b * ho * wo * row {
            candle_core::bail!("col2im: {} values for a {:?} image", cols.len(), self.input);
        }
        let mut x = vec![0f32; b * h * w * c];
        // One image per task: each image's sums are independent, and the order of additions
        // within an image is fixed, so the result does not depend on the thread count.
        x.par_chunks_mut(h * w * c)
            .enumerate()
            .for_each(|(bi, image)| {
                let cols = &cols[bi * ho * wo * row..(bi + 1) * ho * wo * row];
                for oy in 0..ho {
                    for ox in 0..wo {
                        let src_row = &cols[(oy * wo + ox) * row..(oy * wo + ox + 1) * row];
                        for_each_tap((oy, ox), s, (h, w), |tap, pixel| {
                            let src = &src_row[tap * c..(tap + 1) * c];
                            for (d, v) in image[pixel * c..(pixel + 1) * c].iter_mut().zip(src) {
                                *d += v;
                            }
                        });
                    }
                }
            });
        Ok((CpuStorage::F32(x), Shape::from(self.input)))
    }
}

/// Bilinear ×2 upsampling of a channels-last [B, n, n, C] map with fixed interpolation matrices
/// `a` [2n, n] (rows) and `a` again (columns): two matmuls, so it has a backward.
pub fn upsample2x(x: &Tensor, a: &Tensor) -> Result<Tensor> {
    let (b, n, m, c) = x.dims4()?;
    let (n2, n_a) = a.dims2()?;
    if n != n_a || m != n_a {
        candle_core::bail!("upsample2x: a {n}×{m} map with a {n2}×{n_a} matrix");
    }
    // Rows: [2n, n] · [B, n, n·C] → [B, 2n, n·C].
    let rows = a.broadcast_matmul(&x.reshape((b, n, m * c))?)?;
    // Columns: [2n, n] · [B·2n, n, C] → [B·2n, 2n, C].
    let cols = a.broadcast_matmul(&rows.reshape((b * n2, m, c))?)?;
    cols.reshape((b, n2, n2, c))
}

#[cfg(test)]
mod tests {
    use super::super::fused::test_support::{max_diff, values};
    use super::*;
    use candle_core::{Device, Var};

    /// Same values and gradients as candle's conv2d (NCHW) for strides 1 and 2, odd and even
    /// sizes.
    #[test]
    fn matches_candle_conv2d_values_and_gradients() {
        let dev = Device::Cpu;
        for (h, w, stride) in [(8, 8, 1), (8, 8, 2), (7, 5, 2), (5, 6, 1)] {
            let (c_in, c_out, b) = (3, 4, 2);
            let x = Var::from_vec(values(b * c_in * h * w, 1), (b, c_in, h, w), &dev).unwrap();
            let weight =
                Var::from_vec(values(c_out * c_in * 9, 2), (c_out, c_in, 3, 3), &dev).unwrap();
            let bias = Var::from_vec(values(c_out, 3), c_out, &dev).unwrap();
            let reference = x
                .conv2d(&weight, 1, stride, 1, 1)
                .unwrap()
                .broadcast_add(&bias.reshape((1, c_out, 1, 1)).unwrap())
                .unwrap()
                .relu()
                .unwrap();
            let ours = conv3x3(
                &x.permute((0, 2, 3, 1)).unwrap(),
                &weight,
                &bias,
                stride,
                Activation::Relu,
            )
            .unwrap()
            .permute((0, 3, 1, 2))
            .unwrap();
            assert_eq!(ours.dims(), reference.dims());
            assert!(max_diff(&ours, &reference) < 1e-4);
            let probe = Tensor::from_vec(values(ours.elem_count(), 4), ours.dims(), &dev).unwrap();
            let g_ref = (reference * &probe)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let g_ours = (ours.contiguous().unwrap() * &probe)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            for v in [x.as_tensor(), weight.as_tensor(), bias.as_tensor()] {
                let d = max_diff(g_ref.get(v).unwrap(), g_ours.get(v).unwrap());
                assert!(
                    d < 1e-3,
                    "gradient differs by {d} at {h}×{w} stride {stride}"
                );
            }
        }
    }

    #[test]
    fn upsampling_a_constant_map_keeps_it_constant() {
        let dev = Device::Cpu;
        let a = Tensor::from_vec(super::super::encoder::upsample_matrix(4), (8, 4), &dev).unwrap();
        let x = Tensor::full(0.7f32, (2, 4, 4, 3), &dev).unwrap();
        let y = upsample2x(&x, &a).unwrap();
        assert_eq!(y.dims(), &[2, 8, 8, 3]);
        let v = y.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(v.iter().all(|x| (x - 0.7).abs() < 1e-6));
    }
}
