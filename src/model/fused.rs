//! A fused dense layer, y = act(x·W + b), as one candle op with a hand-written backward.
//!
//! Why: candle builds a layer from `matmul`, `broadcast_add` and `relu`. On this CPU the matmul
//! is the cheap part: the backward of `broadcast_add` sums the gradient over rows with a strided
//! reduction, about 50× slower than the same sum as a gemm with a row of ones, and `relu`'s
//! backward takes four element-wise passes (`docs/speed.md`, "Why the hot paths look as they
//! do"). Training spends most of
//! its rays in such layers (colour/ordering heads, compositor, light fields), so here
//! - forward: one gemm straight into the output, then one pass adding the bias (and ReLU);
//! - backward: one pass masking the gradient by the ReLU, two gemms for the input and weight
//!   gradients, and the bias gradient as a gemm with a row of ones.
//!
//! Shapes: x [N, in] with W [in, out] and b [out] (or [1, out]); or, batched, x [S, N, in] with
//! W [S, in, out] and b [S, 1, out]. W may be any strided view (e.g. a `Linear` weight [out, in]
//! passed as `weight.t()`), x and b are made contiguous. f32 on the CPU; anything else falls back
//! to the plain composition of candle ops, which computes the same function.

use candle_core::{CpuStorage, CustomOp2, CustomOp3, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// The non-linearity after the affine map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    Identity,
    Relu,
}

/// How the op's weight argument is laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum WeightLayout {
    /// W [in, out] (or [S, in, out]), any strides.
    InOut,
    /// A `Linear` weight [out, in], used as its transpose: the weight's gradient is made in
    /// this layout, so candle never adds a transposed gradient with a strided pass.
    OutIn,
}

/// y = act(x·W + b); see the module documentation for the shapes.
pub fn dense(x: &Tensor, w: &Tensor, b: &Tensor, act: Activation) -> Result<Tensor> {
    check_shapes(x, w, b)?;
    affine(x, w, b, act, WeightLayout::InOut)
}

/// y = act(x·Wᵀ + b) for a `Linear`-layout weight W [out, in]: x [N, in], b [out].
///
/// The same function as `dense(x, &weight.t()?, b, act)`, but the weight's gradient is made
/// [out, in] and contiguous. Through `.t()` candle adds it into a zero tensor twice, once through
/// a strided transpose: on the hypernetworks' heads (millions of weights) that was a tenth of a
/// training step.
pub fn linear(x: &Tensor, weight: &Tensor, b: &Tensor, act: Activation) -> Result<Tensor> {
    if x.rank() != 2 {
        candle_core::bail!("linear: x must be [N, in], got {:?}", x.dims());
    }
    check_shapes(x, &weight.t()?, b)?;
    affine(x, &weight.contiguous()?, b, act, WeightLayout::OutIn)
}

/// The fused op for f32 on the CPU; anything else the plain composition of candle ops, which
/// computes the same function. Shapes are checked by the callers.
fn affine(
    x: &Tensor,
    w: &Tensor,
    b: &Tensor,
    act: Activation,
    weight: WeightLayout,
) -> Result<Tensor> {
    let x = x.contiguous()?;
    let b = b.contiguous()?;
    if x.device().is_cpu() && x.dtype() == DType::F32 && w.dtype() == DType::F32 {
        return x.apply_op3(w, &b, Dense { act, weight });
    }
    let w_in_out = match weight {
        WeightLayout::InOut => w.clone(),
        WeightLayout::OutIn => w.t()?,
    };
    let y = x.matmul(&w_in_out)?.broadcast_add(&b)?;
    match act {
        Activation::Identity => Ok(y),
        Activation::Relu => y.relu(),
    }
}

fn check_shapes(x: &Tensor, w: &Tensor, b: &Tensor) -> Result<()> {
    let ok = match (x.dims(), w.dims()) {
        ([_, i], [wi, o]) => i == wi && b.elem_count() == *o,
        ([s, _, i], [ws, wi, o]) => s == ws && i == wi && b.elem_count() == s * o,
        _ => false,
    };
    if !ok {
        candle_core::bail!(
            "dense: shapes x {:?}, w {:?}, b {:?} do not fit x·W + b",
            x.dims(),
            w.dims(),
            b.dims()
        );
    }
    Ok(())
}

fn f32_slice<'a>(storage: &'a CpuStorage, what: &str) -> Result<&'a [f32]> {
    match storage {
        CpuStorage::F32(v) => Ok(v.as_slice()),
        _ => candle_core::bail!("dense: {what} must be f32"),
    }
}

fn gemm_parallelism(work: usize) -> gemm::Parallelism {
    // rayon's threads, not candle's: colf runs candle's element-wise pool on the caller's thread
    // alone (`src/alloc.rs`), and the hypernetworks' heads, the largest products of a refinement
    // step outside the decode kernel, would otherwise run on one core while the other waits.
    // The gemm splits the output among threads and sums every element in the same order, so the
    // bytes do not depend on the thread count.
    let threads = rayon::current_num_threads();
    // Threads only pay off on large products (as candle's own matmul decides).
    if threads > 1 && work > 1 << 16 {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    }
}

/// dst [m, n] (contiguous, not read) = a [m, k] · b [k, n], each operand a pointer with its row
/// and column strides.
///
/// # Safety
/// The pointers must cover those elements at those strides, and dst m·n writable ones.
unsafe fn strided_gemm(
    (m, n, k): (usize, usize, usize),
    dst: *mut f32,
    (a, a_rs, a_cs): (*const f32, isize, isize),
    (b, b_rs, b_cs): (*const f32, isize, isize),
    parallelism: gemm::Parallelism,
) {
    gemm::gemm(
        m,
        n,
        k,
        dst,
        1,
        n as isize,
        false,
        a,
        a_cs,
        a_rs,
        b,
        b_cs,
        b_rs,
        0.0,
        1.0,
        false,
        false,
        false,
        parallelism,
    );
}

struct Dense {
    act: Activation,
    weight: WeightLayout,
}

impl CustomOp3 for Dense {
    fn name(&self) -> &'static str {
        "colf-dense"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bs: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (x_start, _) = xl
            .contiguous_offsets()
            .ok_or_else(|| candle_core::Error::Msg("dense: x must be contiguous".into()))?;
        let (b_start, _) = bl
            .contiguous_offsets()
            .ok_or_else(|| candle_core::Error::Msg("dense: b must be contiguous".into()))?;
        let (x, w, b) = (
            f32_slice(xs, "x")?,
            f32_slice(ws, "w")?,
            f32_slice(bs, "b")?,
        );
        let (batch, n, k, out, out_shape) = match (xl.dims(), wl.dims(), self.weight) {
            (&[n, k], &[_, o], WeightLayout::InOut) | (&[n, k], &[o, _], WeightLayout::OutIn) => {
                (1, n, k, o, Shape::from((n, o)))
            }
            (&[s, n, k], &[_, _, o], WeightLayout::InOut) => (s, n, k, o, Shape::from((s, n, o))),
            _ => candle_core::bail!("dense: unsupported ranks"),
        };
        let w_stride = wl.stride();
        let rank = w_stride.len();
        // Strides of W as the [in, out] matrix the gemm reads.
        let (w_rs, w_cs) = match self.weight {
            WeightLayout::InOut => (w_stride[rank - 2] as isize, w_stride[rank - 1] as isize),
            WeightLayout::OutIn => (w_stride[rank - 1] as isize, w_stride[rank - 2] as isize),
        };
        let w_batch = if rank == 3 { w_stride[0] } else { 0 };
        let len = batch * n * out;
        let mut y: Vec<f32> = Vec::with_capacity(len);
        // SAFETY: every element is written by the gemms below (read_dst = false, beta·lhs·rhs
        // only) before anything reads it; skipping the zero fill saves a pass over the output.
        #[allow(clippy::uninit_vec)]
        unsafe {
            y.set_len(len);
        }
        let parallelism = gemm_parallelism(n * k * out);
        for s in 0..batch {
            // SAFETY: the pointers cover [n, k], [k, out] (with w's strides, inside w's
            // storage as its layout guarantees) and [n, out] elements; dst is not read.
            unsafe {
                strided_gemm(
                    (n, out, k),
                    y.as_mut_ptr().add(s * n * out),
                    (x.as_ptr().add(x_start + s * n * k), k as isize, 1),
                    (w.as_ptr().add(wl.start_offset() + s * w_batch), w_rs, w_cs),
                    parallelism,
                );
            }
        }
        let bias = &b[b_start..b_start + batch * out];
        let relu = self.act == Activation::Relu;
        y.par_chunks_mut(n * out)
            .zip(bias.par_chunks(out))
            .for_each(|(block, bias)| {
                for row in block.chunks_exact_mut(out) {
                    for (v, b) in row.iter_mut().zip(bias) {
                        let t = *v + b;
                        *v = if relu { t.max(0.0) } else { t };
                    }
                }
            });
        Ok((CpuStorage::F32(y), out_shape))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        res: &Tensor,
        grad_res: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad_res = grad_res.contiguous()?;
        let g = match self.act {
            Activation::Identity => grad_res,
            Activation::Relu => grad_res.apply_op2_no_bwd(res, &ReluMask)?,
        };
        // Only what feeds a variable: candle asks for every argument's gradient, and refinement's
        // constant weights would otherwise cost a gemm each (and a zeroed buffer to add it to).
        let grad_x = if x.track_op() {
            Some(match self.weight {
                WeightLayout::InOut => product(&g, &w.t()?)?,
                WeightLayout::OutIn => product(&g, w)?,
            })
        } else {
            None
        };
        let grad_w = if w.track_op() {
            Some(match self.weight {
                WeightLayout::InOut => product(&x.t()?, &g)?,
                WeightLayout::OutIn => product(&g.t()?, x)?,
            })
        } else {
            None
        };
        let grad_b = if b.track_op() {
            let rows = g.dim(g.rank() - 2)?;
            let ones_shape: Vec<usize> = match g.dims() {
                [_, _] => vec![1, rows],
                [s, _, _] => vec![*s, 1, rows],
                _ => candle_core::bail!("dense: unsupported rank"),
            };
            let ones = Tensor::ones(ones_shape, DType::F32, g.device())?;
            Some(ones.matmul(&g)?.reshape(b.shape())?)
        } else {
            None
        };
        Ok((grad_x, grad_w, grad_b))
    }
}

/// a·b for the backward: one gemm over the strided views on rayon's threads for 2-D f32
/// operands on the CPU (candle's matmul would run on its one-thread pool), candle's matmul for
/// anything else.
fn product(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    if a.rank() == 2 && a.device().is_cpu() && a.dtype() == DType::F32 && b.dtype() == DType::F32 {
        a.apply_op2_no_bwd(b, &Product)
    } else {
        a.matmul(b)
    }
}

/// a [m, k] · b [k, n], any strides, into a contiguous [m, n].
struct Product;

impl CustomOp2 for Product {
    fn name(&self) -> &'static str {
        "colf-product"
    }

    fn cpu_fwd(
        &self,
        a_storage: &CpuStorage,
        al: &Layout,
        b_storage: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (&[m, k], &[kb, n]) = (al.dims(), bl.dims()) else {
            candle_core::bail!(
                "product: 2-D operands only, got {:?} and {:?}",
                al.dims(),
                bl.dims()
            );
        };
        if k != kb {
            candle_core::bail!(
                "product: shapes {:?} and {:?} do not fit",
                al.dims(),
                bl.dims()
            );
        }
        let (a, b) = (f32_slice(a_storage, "a")?, f32_slice(b_storage, "b")?);
        let (a_stride, b_stride) = (al.stride(), bl.stride());
        if k == 0 {
            return Ok((CpuStorage::F32(vec![0f32; m * n]), Shape::from((m, n))));
        }
        let mut y: Vec<f32> = Vec::with_capacity(m * n);
        // SAFETY: the gemm below writes every element (read_dst = false) before anything reads
        // it; the weight gradients are megabytes, and a zero fill would be a pass of its own.
        #[allow(clippy::uninit_vec)]
        unsafe {
            y.set_len(m * n);
        }
        // SAFETY: the layouts guarantee that [m, k] and [k, n] elements at these strides lie
        // inside the storages; dst is [m, n] contiguous and not read (read_dst = false).
        unsafe {
            strided_gemm(
                (m, n, k),
                y.as_mut_ptr(),
                (
                    a.as_ptr().add(al.start_offset()),
                    a_stride[0] as isize,
                    a_stride[1] as isize,
                ),
                (
                    b.as_ptr().add(bl.start_offset()),
                    b_stride[0] as isize,
                    b_stride[1] as isize,
                ),
                gemm_parallelism(m * n * k),
            );
        }
        Ok((CpuStorage::F32(y), Shape::from((m, n))))
    }
}

/// grad · [res > 0], in one pass (res is the ReLU's output).
struct ReluMask;

impl CustomOp2 for ReluMask {
    fn name(&self) -> &'static str {
        "colf-relu-mask"
    }

    fn cpu_fwd(
        &self,
        gs: &CpuStorage,
        gl: &Layout,
        rs: &CpuStorage,
        rl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (Some((g0, g1)), Some((r0, r1))) = (gl.contiguous_offsets(), rl.contiguous_offsets())
        else {
            candle_core::bail!("relu mask: inputs must be contiguous");
        };
        let (g, r) = (
            &f32_slice(gs, "grad")?[g0..g1],
            &f32_slice(rs, "res")?[r0..r1],
        );
        let out: Vec<f32> = g
            .par_iter()
            .zip(r.par_iter())
            .with_min_len(1 << 14)
            .map(|(g, r)| if *r > 0.0 { *g } else { 0.0 })
            .collect();
        Ok((CpuStorage::F32(out), gl.shape().clone()))
    }
}

/// Helpers shared by the kernels' tests.
#[cfg(test)]
pub(crate) mod test_support {
    use candle_core::Tensor;

    pub fn values(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| (((i as u32).wrapping_mul(2654435761) ^ seed) % 2001) as f32 / 1000.0 - 1.0)
            .collect()
    }

    pub fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }
}

#[cfg(test)]
mod tests {
    use super::test_support::{max_diff, values};
    use super::*;
    use candle_core::{Device, Var};

    /// The fused op and the plain composition agree on values and on every gradient.
    fn compare(x_dims: &[usize], w_dims: &[usize], b_dims: &[usize], transpose_w: bool) {
        let dev = Device::Cpu;
        let n = |d: &[usize]| d.iter().product::<usize>();
        let x = Var::from_vec(values(n(x_dims), 1), x_dims, &dev).unwrap();
        let w_store = if transpose_w {
            // Stored [out, in] like a `Linear` weight, used through `.t()`.
            let (i, o) = (w_dims[0], w_dims[1]);
            Var::from_vec(values(i * o, 2), (o, i), &dev).unwrap()
        } else {
            Var::from_vec(values(n(w_dims), 2), w_dims, &dev).unwrap()
        };
        let w = if transpose_w {
            w_store.t().unwrap()
        } else {
            w_store.as_tensor().clone()
        };
        let b = Var::from_vec(values(n(b_dims), 3), b_dims, &dev).unwrap();
        for act in [Activation::Identity, Activation::Relu] {
            let weight = Tensor::from_vec(
                values(
                    n(x_dims) / x_dims[x_dims.len() - 1] * w_dims[w_dims.len() - 1],
                    4,
                ),
                {
                    let mut d = x_dims.to_vec();
                    *d.last_mut().unwrap() = w_dims[w_dims.len() - 1];
                    d
                },
                &dev,
            )
            .unwrap();
            let fused = dense(&x, &w, &b, act).unwrap();
            let plain = x.matmul(&w).unwrap().broadcast_add(&b).unwrap();
            let plain = if act == Activation::Relu {
                plain.relu().unwrap()
            } else {
                plain
            };
            assert!(max_diff(&fused, &plain) < 1e-4);
            let gf = (fused * &weight)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let gp = (plain * &weight)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            for v in [x.as_tensor(), w_store.as_tensor(), b.as_tensor()] {
                let (a, c) = (gf.get(v).unwrap(), gp.get(v).unwrap());
                assert_eq!(a.dims(), c.dims());
                assert!(
                    max_diff(a, c) < 1e-3,
                    "gradient differs by {}",
                    max_diff(a, c)
                );
            }
        }
    }

    #[test]
    fn matches_matmul_bias_relu_in_2d() {
        compare(&[37, 5], &[5, 9], &[9], false);
        compare(&[300, 16], &[16, 8], &[8], true);
    }

    #[test]
    fn matches_batched_matmul_bias_relu() {
        compare(&[3, 41, 6], &[3, 6, 10], &[3, 1, 10], false);
    }

    /// `linear` on a [out, in] weight: the values and gradients of `x·Wᵀ + b`, the weight's
    /// gradient in the weight's own layout; constants get no gradient at all.
    #[test]
    fn linear_matches_the_transposed_matmul() {
        let dev = Device::Cpu;
        let (n, i, o) = (29, 7, 11);
        let x = Var::from_vec(values(n * i, 1), (n, i), &dev).unwrap();
        let w = Var::from_vec(values(o * i, 2), (o, i), &dev).unwrap();
        let b = Var::from_vec(values(o, 3), o, &dev).unwrap();
        let weight = Tensor::from_vec(values(n * o, 4), (n, o), &dev).unwrap();
        for act in [Activation::Identity, Activation::Relu] {
            let fused = linear(&x, &w, &b, act).unwrap();
            let plain = x
                .matmul(&w.t().unwrap())
                .unwrap()
                .broadcast_add(&b)
                .unwrap();
            let plain = match act {
                Activation::Relu => plain.relu().unwrap(),
                Activation::Identity => plain,
            };
            assert!(max_diff(&fused, &plain) < 1e-5);
            let loss = |y: Tensor| (y * &weight).unwrap().sum_all().unwrap();
            let gf = loss(fused).backward().unwrap();
            let gp = loss(plain).backward().unwrap();
            for v in [x.as_tensor(), w.as_tensor(), b.as_tensor()] {
                let (a, c) = (gf.get(v).unwrap(), gp.get(v).unwrap());
                assert_eq!(a.dims(), c.dims());
                assert!(a.is_contiguous());
                assert!(max_diff(a, c) < 1e-4, "{}", max_diff(a, c));
            }
        }
        // A constant weight and bias (as refinement's) get no gradient; x still does.
        let (w_const, b_const) = (w.as_tensor().detach(), b.as_tensor().detach());
        let y = linear(&x, &w_const, &b_const, Activation::Relu).unwrap();
        let grads = (y * &weight)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(grads.get(&w_const).is_none() && grads.get(&b_const).is_none());
        assert!(grads.get(x.as_tensor()).is_some());
    }

    /// The backward's products on rayon's threads: candle's matmul within rounding, for
    /// transposed views too, and the same bytes on one thread as on three.
    #[test]
    fn products_are_the_matmul_and_independent_of_the_thread_count() {
        let dev = Device::Cpu;
        let (m, k, n) = (12, 64, 700); // m·k·n above the threshold for threads
        let a = Tensor::from_vec(values(k * m, 5), (k, m), &dev).unwrap();
        let b = Tensor::from_vec(values(k * n, 6), (k, n), &dev).unwrap();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let y = product(&a.t().unwrap(), &b).unwrap();
                y.flatten_all().unwrap().to_vec1::<f32>().unwrap()
            })
        };
        let (one, three) = (run(1), run(3));
        assert_eq!(one, three);
        let plain = a.t().unwrap().matmul(&b).unwrap();
        let fused = Tensor::from_vec(one, (m, n), &dev).unwrap();
        assert!(max_diff(&fused, &plain) < 1e-4);
        // Operands that do not fit are refused, not read out of bounds.
        assert!(product(&a, &b.t().unwrap()).is_err());
    }

    #[test]
    fn refuses_mismatched_shapes() {
        let dev = Device::Cpu;
        let x = Tensor::zeros((4, 3), DType::F32, &dev).unwrap();
        let w = Tensor::zeros((5, 2), DType::F32, &dev).unwrap();
        let b = Tensor::zeros(2, DType::F32, &dev).unwrap();
        assert!(dense(&x, &w, &b, Activation::Relu).is_err());
    }
}
