//! How far apart two results are. Each helper asserts that the shapes agree: comparing a truncated result
//! against the reference must fail, not pass on the common prefix.

use candle_core::Tensor;

/// The largest absolute difference of two equally long slices (0 for empty ones).
#[track_caller]
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// ‖a − b‖₂ / ‖b‖₂ of two equally long slices, summed in f64 (b = 0 counts as a norm of the smallest
/// positive f32, so a nonzero a against a zero b is a large error, not NaN).
#[track_caller]
pub fn relative_l2(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    let (mut diff, mut norm) = (0.0f64, 0.0f64);
    for (&x, &y) in a.iter().zip(b) {
        diff += f64::from(x - y).powi(2);
        norm += f64::from(y).powi(2);
    }
    (diff / norm.max(f64::from(f32::MIN_POSITIVE))).sqrt() as f32
}

/// The values of a tensor of any shape and float type, as f32 in row-major order.
pub fn values(t: &Tensor) -> Vec<f32> {
    t.to_dtype(candle_core::DType::F32)
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1())
        .unwrap_or_else(|e| panic!("reading a tensor of shape {:?}: {e}", t.dims()))
}

/// [`max_abs_diff`] of two tensors of the same shape.
#[track_caller]
pub fn tensor_max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims(), "shapes differ");
    max_abs_diff(&values(a), &values(b))
}

/// [`relative_l2`] of two tensors of the same shape.
#[track_caller]
pub fn tensor_relative_l2(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims(), "shapes differ");
    relative_l2(&values(a), &values(b))
}

/// The largest absolute difference relative to `want`'s largest magnitude (floored at 1e-6): the GPU
/// tests' measure against the CPU.
#[track_caller]
pub fn tensor_relative_error(got: &Tensor, want: &Tensor) -> f32 {
    tensor_max_abs_diff(got, want) / tensor_max_abs(want).max(1e-6)
}

/// The largest absolute value of a tensor (0 for an empty one).
pub fn tensor_max_abs(t: &Tensor) -> f32 {
    values(t).iter().fold(0.0, |m, v| m.max(v.abs()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn differences_of_slices_and_tensors_agree() {
        let a = [1.0, -2.0, 3.5];
        let b = [1.5, -2.0, 3.0];
        assert_eq!(max_abs_diff(&a, &b), 0.5);
        let want = (0.5f64 / (1.5f64 * 1.5 + 4.0 + 9.0)).sqrt() as f32;
        assert!((relative_l2(&a, &b) - want).abs() < 1e-7);
        let ta = Tensor::new(&a, &Device::Cpu)
            .unwrap()
            .reshape((3, 1))
            .unwrap();
        let tb = Tensor::new(&b, &Device::Cpu)
            .unwrap()
            .reshape((3, 1))
            .unwrap();
        assert_eq!(tensor_max_abs_diff(&ta, &tb), 0.5);
        assert_eq!(tensor_relative_l2(&ta, &tb), relative_l2(&a, &b));
        assert_eq!(tensor_max_abs(&ta), 3.5);
        assert!(relative_l2(&[1.0], &[0.0]) > 1e10);
    }

    #[test]
    #[should_panic(expected = "lengths differ")]
    fn a_shorter_result_is_not_compared_on_the_common_prefix() {
        max_abs_diff(&[1.0], &[1.0, 2.0]);
    }
}
