//! The Inception-v3 feature extractor of FID and KID: the network of the TF "2015-12-05" graph
//! that clean-fid runs (as TorchScript) and pytorch-fid ports as `FIDInceptionA/C/E_1/E_2`
//! (`cleanfid/inception_pytorch.py`): torchvision's Inception3 blocks with average pools that
//! leave the zero padding out of the count and a max pool in the last block's pool branch. The
//! features are the 2048-d global average pool after `Mixed_7c`.
//!
//! Input preparation is clean-fid's "clean" mode: each RGB u8 frame resized per channel in float
//! with Pillow's bicubic filter to 299×299 ([`super::resize`]), then `(x − 128) / 128`.
//!
//! Weights: torchvision's Inception3 names (`Conv2d_1a_3x3.conv.weight`, `Mixed_5b.branch1x1.bn.
//! running_mean`, …) in one safetensors, as `scripts/convert_eval_weights.py inception` writes
//! it from pytorch-fid's `pt_inception-2015-12-05-6726825d.pth` or clean-fid's TorchScript file.

use std::path::Path;

use image::RgbImage;
use tch::{Device, Tensor};

use super::WeightFile;
use crate::error::{Error, Result};

/// The input side clean-fid resizes to.
pub const INPUT_SIZE: usize = 299;
/// Width of the pool features.
pub const FEATURES: i64 = 2048;
/// clean-fid's `InceptionV3W` normalisation, `(x − 128) / 128` on [0, 255] values.
const PIXEL_CENTER: f64 = 128.0;
/// torchvision's `BasicConv2d` batch-norm epsilon.
const BN_EPS: f64 = 1e-3;

/// How to make the weight file, for the missing-file message.
pub const HOW_TO_GET: &str = "convert clean-fid's TorchScript Inception (/tmp/inception-2015-12-05.pt, from any \
     earlier clean-fid run) or pytorch-fid's pt_inception-2015-12-05-6726825d.pth (~/.cache/torch/hub/checkpoints/) \
     with `scripts/convert_eval_weights.py inception --source FILE --out FILE`";

/// Conv (no bias) + batch norm (inference) + ReLU, torchvision's `BasicConv2d`.
#[derive(Debug)]
struct BasicConv {
    weight: Tensor,
    bn: [Tensor; 4],
    stride: [i64; 2],
    padding: [i64; 2],
}

impl BasicConv {
    fn load(
        file: &WeightFile,
        name: &str,
        input: i64,
        output: i64,
        kernel: [i64; 2],
        stride: i64,
        padding: [i64; 2],
    ) -> Result<Self> {
        let bn = |p: &str| file.get(&format!("{name}.bn.{p}"), &[output]);
        Ok(Self {
            weight: file.get(&format!("{name}.conv.weight"), &[output, input, kernel[0], kernel[1]])?,
            bn: [bn("weight")?, bn("bias")?, bn("running_mean")?, bn("running_var")?],
            stride: [stride; 2],
            padding,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = x.f_conv2d(&self.weight, None::<Tensor>, self.stride, self.padding, [1, 1], 1)?;
        let [w, b, m, v] = &self.bn;
        Ok(Tensor::f_batch_norm(&y, Some(w), Some(b), Some(m), Some(v), false, 0.0, BN_EPS, false)?.relu())
    }
}

fn avg_pool_same(x: &Tensor) -> Result<Tensor> {
    // TF's average pool ignores the padding (count_include_pad=False), the FID variants' patch.
    Ok(x.f_avg_pool2d([3, 3], [1, 1], [1, 1], false, false, None)?)
}

fn max_pool_stride2(x: &Tensor) -> Result<Tensor> {
    Ok(x.f_max_pool2d([3, 3], [2, 2], [0, 0], [1, 1], false)?)
}

/// One Inception block: its branches, each a chain of convs with an optional pool first, or a
/// split into two parallel convs at the end (the E blocks).
#[derive(Debug)]
struct Branch {
    pool: Pool,
    chain: Vec<BasicConv>,
    split: Vec<BasicConv>,
}

#[derive(Debug, Clone, Copy)]
enum Pool {
    None,
    AvgSame,
    MaxSame,
    MaxStride2,
}

impl Branch {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut y = match self.pool {
            Pool::None => x.shallow_clone(),
            Pool::AvgSame => avg_pool_same(x)?,
            Pool::MaxSame => x.f_max_pool2d([3, 3], [1, 1], [1, 1], [1, 1], false)?,
            Pool::MaxStride2 => max_pool_stride2(x)?,
        };
        for conv in &self.chain {
            y = conv.forward(&y)?;
        }
        if self.split.is_empty() {
            return Ok(y);
        }
        let parts = self.split.iter().map(|c| c.forward(&y)).collect::<Result<Vec<_>>>()?;
        Ok(Tensor::f_cat(&parts, 1)?)
    }
}

/// A conv spec: suffix, in, out, kernel, stride, padding.
type Spec<'a> = (&'a str, i64, i64, [i64; 2], i64, [i64; 2]);

fn branch(file: &WeightFile, block: &str, pool: Pool, chain: &[Spec], split: &[Spec]) -> Result<Branch> {
    let load = |s: &[Spec]| -> Result<Vec<BasicConv>> {
        s.iter().map(|&(n, i, o, k, st, p)| BasicConv::load(file, &format!("{block}.{n}"), i, o, k, st, p)).collect()
    };
    Ok(Branch { pool, chain: load(chain)?, split: load(split)? })
}

const K1: [i64; 2] = [1, 1];
const K3: [i64; 2] = [3, 3];
const K5: [i64; 2] = [5, 5];
const K17: [i64; 2] = [1, 7];
const K71: [i64; 2] = [7, 1];
const K13: [i64; 2] = [1, 3];
const K31: [i64; 2] = [3, 1];
const P0: [i64; 2] = [0, 0];
const P1: [i64; 2] = [1, 1];
const P2: [i64; 2] = [2, 2];
const P03: [i64; 2] = [0, 3];
const P30: [i64; 2] = [3, 0];
const P01: [i64; 2] = [0, 1];
const P10: [i64; 2] = [1, 0];

/// `FIDInceptionA(in, pool_features)`.
fn block_a(f: &WeightFile, name: &str, c: i64, pool: i64) -> Result<Vec<Branch>> {
    Ok(vec![
        branch(f, name, Pool::None, &[("branch1x1", c, 64, K1, 1, P0)], &[])?,
        branch(f, name, Pool::None, &[("branch5x5_1", c, 48, K1, 1, P0), ("branch5x5_2", 48, 64, K5, 1, P2)], &[])?,
        branch(
            f,
            name,
            Pool::None,
            &[
                ("branch3x3dbl_1", c, 64, K1, 1, P0),
                ("branch3x3dbl_2", 64, 96, K3, 1, P1),
                ("branch3x3dbl_3", 96, 96, K3, 1, P1),
            ],
            &[],
        )?,
        branch(f, name, Pool::AvgSame, &[("branch_pool", c, pool, K1, 1, P0)], &[])?,
    ])
}

/// torchvision `InceptionB(288)` (Mixed_6a).
fn block_b(f: &WeightFile, name: &str, c: i64) -> Result<Vec<Branch>> {
    Ok(vec![
        branch(f, name, Pool::None, &[("branch3x3", c, 384, K3, 2, P0)], &[])?,
        branch(
            f,
            name,
            Pool::None,
            &[
                ("branch3x3dbl_1", c, 64, K1, 1, P0),
                ("branch3x3dbl_2", 64, 96, K3, 1, P1),
                ("branch3x3dbl_3", 96, 96, K3, 2, P0),
            ],
            &[],
        )?,
        Branch { pool: Pool::MaxStride2, chain: vec![], split: vec![] },
    ])
}

/// `FIDInceptionC(768, channels_7x7)`.
fn block_c(f: &WeightFile, name: &str, c: i64, c7: i64) -> Result<Vec<Branch>> {
    Ok(vec![
        branch(f, name, Pool::None, &[("branch1x1", c, 192, K1, 1, P0)], &[])?,
        branch(
            f,
            name,
            Pool::None,
            &[
                ("branch7x7_1", c, c7, K1, 1, P0),
                ("branch7x7_2", c7, c7, K17, 1, P03),
                ("branch7x7_3", c7, 192, K71, 1, P30),
            ],
            &[],
        )?,
        branch(
            f,
            name,
            Pool::None,
            &[
                ("branch7x7dbl_1", c, c7, K1, 1, P0),
                ("branch7x7dbl_2", c7, c7, K71, 1, P30),
                ("branch7x7dbl_3", c7, c7, K17, 1, P03),
                ("branch7x7dbl_4", c7, c7, K71, 1, P30),
                ("branch7x7dbl_5", c7, 192, K17, 1, P03),
            ],
            &[],
        )?,
        branch(f, name, Pool::AvgSame, &[("branch_pool", c, 192, K1, 1, P0)], &[])?,
    ])
}

/// torchvision `InceptionD(768)` (Mixed_7a).
fn block_d(f: &WeightFile, name: &str, c: i64) -> Result<Vec<Branch>> {
    Ok(vec![
        branch(f, name, Pool::None, &[("branch3x3_1", c, 192, K1, 1, P0), ("branch3x3_2", 192, 320, K3, 2, P0)], &[])?,
        branch(
            f,
            name,
            Pool::None,
            &[
                ("branch7x7x3_1", c, 192, K1, 1, P0),
                ("branch7x7x3_2", 192, 192, K17, 1, P03),
                ("branch7x7x3_3", 192, 192, K71, 1, P30),
                ("branch7x7x3_4", 192, 192, K3, 2, P0),
            ],
            &[],
        )?,
        Branch { pool: Pool::MaxStride2, chain: vec![], split: vec![] },
    ])
}

/// `FIDInceptionE_1` (average pool branch) or `FIDInceptionE_2` (max pool branch).
fn block_e(f: &WeightFile, name: &str, c: i64, pool: Pool) -> Result<Vec<Branch>> {
    Ok(vec![
        branch(f, name, Pool::None, &[("branch1x1", c, 320, K1, 1, P0)], &[])?,
        branch(
            f,
            name,
            Pool::None,
            &[("branch3x3_1", c, 384, K1, 1, P0)],
            &[("branch3x3_2a", 384, 384, K13, 1, P01), ("branch3x3_2b", 384, 384, K31, 1, P10)],
        )?,
        branch(
            f,
            name,
            Pool::None,
            &[("branch3x3dbl_1", c, 448, K1, 1, P0), ("branch3x3dbl_2", 448, 384, K3, 1, P1)],
            &[("branch3x3dbl_3a", 384, 384, K13, 1, P01), ("branch3x3dbl_3b", 384, 384, K31, 1, P10)],
        )?,
        branch(f, name, pool, &[("branch_pool", c, 192, K1, 1, P0)], &[])?,
    ])
}

/// The FID Inception up to its pool features.
#[derive(Debug)]
pub struct FidInception {
    stem: Vec<(BasicConv, bool)>,
    blocks: Vec<Vec<Branch>>,
    device: Device,
}

impl FidInception {
    /// Loads `path`, checking every tensor's name and shape.
    pub fn load(path: &Path, device: Device) -> Result<Self> {
        let f = WeightFile::open(path, device, "Inception (FID/KID)", HOW_TO_GET)?;
        // (conv, followed by the stride-2 max pool)
        let stem = vec![
            (BasicConv::load(&f, "Conv2d_1a_3x3", 3, 32, K3, 2, P0)?, false),
            (BasicConv::load(&f, "Conv2d_2a_3x3", 32, 32, K3, 1, P0)?, false),
            (BasicConv::load(&f, "Conv2d_2b_3x3", 32, 64, K3, 1, P1)?, true),
            (BasicConv::load(&f, "Conv2d_3b_1x1", 64, 80, K1, 1, P0)?, false),
            (BasicConv::load(&f, "Conv2d_4a_3x3", 80, 192, K3, 1, P0)?, true),
        ];
        let blocks = vec![
            block_a(&f, "Mixed_5b", 192, 32)?,
            block_a(&f, "Mixed_5c", 256, 64)?,
            block_a(&f, "Mixed_5d", 288, 64)?,
            block_b(&f, "Mixed_6a", 288)?,
            block_c(&f, "Mixed_6b", 768, 128)?,
            block_c(&f, "Mixed_6c", 768, 160)?,
            block_c(&f, "Mixed_6d", 768, 160)?,
            block_c(&f, "Mixed_6e", 768, 192)?,
            block_d(&f, "Mixed_7a", 768)?,
            block_e(&f, "Mixed_7b", 1280, Pool::AvgSame)?,
            block_e(&f, "Mixed_7c", 2048, Pool::MaxSame)?,
        ];
        Ok(Self { stem, blocks, device })
    }

    /// Pool features `[N, 2048]` of a normalised `[N, 3, 299, 299]` batch.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let size = x.size();
        let side = INPUT_SIZE as i64;
        if size.len() != 4 || size[1..] != [3, side, side] {
            return Err(Error::Shape {
                tensor: "inception input".to_string(),
                expected: format!("[N, 3, {side}, {side}]"),
                actual: size,
            });
        }
        let mut y = x.shallow_clone();
        for (conv, pool) in &self.stem {
            y = conv.forward(&y)?;
            if *pool {
                y = max_pool_stride2(&y)?;
            }
        }
        for block in &self.blocks {
            let parts = block.iter().map(|b| b.forward(&y)).collect::<Result<Vec<_>>>()?;
            y = Tensor::f_cat(&parts, 1)?;
        }
        Ok(y.f_adaptive_avg_pool2d([1, 1])?.flatten(1, -1))
    }

    /// clean-fid "clean" features `[N, 2048]` of RGB frames (any sizes).
    pub fn features(&self, frames: &[&RgbImage]) -> Result<Tensor> {
        let batch = preprocess(frames, self.device);
        tch::no_grad(|| self.forward(&batch))
    }
}

/// clean-fid's input: the "clean" resize to 299×299 then `(x − 128) / 128`, `[N, 3, 299, 299]`.
/// Frames are resized in parallel (rayon), as clean-fid's data loader does with workers.
pub fn preprocess(frames: &[&RgbImage], device: Device) -> Tensor {
    use rayon::prelude::*;
    let side = INPUT_SIZE;
    let data: Vec<f32> =
        frames.par_iter().map(|f| super::resize::resize_rgb_clean(f, side, side)).collect::<Vec<_>>().concat();
    let tensor = Tensor::from_slice(&data).view([frames.len() as i64, 3, side as i64, side as i64]).to_device(device);
    (tensor - PIXEL_CENTER) / PIXEL_CENTER
}
