//! The vendored candle-core's backward (vendor/candle-core/COLF-PATCH.md) stores a node's first
//! gradient as it is instead of adding it to a zeroed tensor. These graphs check that the
//! gradients are still the textbook ones where a node gets one gradient, where it gets several,
//! and where the gradient arrives as a strided view; and that what is stored is contiguous.

use candle_core::{DType, Device, Tensor, Var};

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn close(got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(want) {
        assert!(
            (g - w).abs() <= 1e-5 * (1.0 + w.abs()),
            "{got:?} vs {want:?}"
        );
    }
}

#[test]
fn one_gradient_several_gradients_and_strided_ones_sum_as_in_the_textbook() {
    let dev = Device::Cpu;
    let a_values = [0.5f32, -1.0, 2.0, 1.5, 0.25, -0.75];
    let b_values = [1.0f32, 2.0, -0.5, 0.0, 3.0, -1.0];
    let a = Var::from_slice(&a_values, (2, 3), &dev).unwrap();
    let b = Var::from_slice(&b_values, (2, 3), &dev).unwrap();
    // a reaches the loss three times (twice through the product, once through the transpose),
    // b once; the transpose hands a strided gradient back to a.
    let product = (a.as_tensor() * b.as_tensor()).unwrap();
    let twice = (&product + &product).unwrap();
    let through_t = a.t().unwrap().sqr().unwrap().sum_all().unwrap();
    let loss = (twice.sum_all().unwrap() + through_t).unwrap();
    let grads = loss.backward().unwrap();

    let grad_a = grads.get(a.as_tensor()).unwrap();
    let grad_b = grads.get(b.as_tensor()).unwrap();
    // d/da = 2 b + 2 a; d/db = 2 a.
    let want_a: Vec<f32> = a_values
        .iter()
        .zip(&b_values)
        .map(|(a, b)| 2.0 * b + 2.0 * a)
        .collect();
    let want_b: Vec<f32> = a_values.iter().map(|a| 2.0 * a).collect();
    close(&values(grad_a), &want_a);
    close(&values(grad_b), &want_b);
    for g in [grad_a, grad_b] {
        assert!(g.is_contiguous());
        assert_eq!(g.dims(), &[2, 3]);
        assert_eq!(g.dtype(), DType::F32);
    }
}

#[test]
fn a_broadcast_gradient_is_stored_with_the_arguments_shape() {
    let dev = Device::Cpu;
    let x = Var::from_slice(&[1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0], (2, 3), &dev).unwrap();
    let bias = Var::from_slice(&[0.5f32, -0.5, 1.0], 3, &dev).unwrap();
    let shifted = x.as_tensor().broadcast_add(bias.as_tensor()).unwrap();
    let loss = shifted.sqr().unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    // d/dbias_j = sum_i 2 (x_ij + bias_j); d/dx = 2 (x + bias).
    close(
        &values(grads.get(bias.as_tensor()).unwrap()),
        &[12.0, 12.0, 22.0],
    );
    let grad_x = grads.get(x.as_tensor()).unwrap();
    let want_x = [3.0, 3.0, 8.0, 9.0, 9.0, 14.0];
    close(&values(grad_x), &want_x);
    assert!(grad_x.is_contiguous());
    // The gradient is the store's own tensor: changing the input afterwards leaves it alone.
    x.set(&Tensor::zeros((2, 3), DType::F32, &dev).unwrap())
        .unwrap();
    close(&values(grad_x), &want_x);
}
