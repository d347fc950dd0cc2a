//! libtorch is linked and computes: a matrix product checked by hand, on the CPU.

use trainer::tch::{Device, Kind, Tensor};

#[test]
fn matmul_matches_a_hand_computation() {
    let a = Tensor::from_slice(&[1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]).reshape([2, 3]);
    let b = Tensor::from_slice(&[7.0f32, 8.0, 9.0, 10.0, 11.0, 12.0]).reshape([3, 2]);
    let product = a.matmul(&b);
    assert_eq!(product.size(), vec![2, 2]);
    assert_eq!(product.kind(), Kind::Float);
    assert_eq!(product.device(), Device::Cpu);
    let values: Vec<f32> = Vec::try_from(product.flatten(0, -1)).unwrap();
    // [1 2 3; 4 5 6] · [7 8; 9 10; 11 12] = [58 64; 139 154]
    assert_eq!(values, vec![58.0, 64.0, 139.0, 154.0]);
}
