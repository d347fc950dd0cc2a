//! LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
//! Metric") as the `lpips` package's `LPIPS(net=..., version="0.1")` computes it: inputs in
//! [-1, 1], its scaling layer, five ReLU taps of torchvision's AlexNet or VGG16 `features`,
//! channel-unit-normalised, squared differences weighted by the v0.1 linear heads (1×1 convs),
//! averaged over space and summed over taps. The spatial map (`spatial=True`: each tap's map
//! bilinearly upsampled to the input size) gives DyCheck's masked mLPIPS as its mean over
//! co-visible pixels.
//!
//! Weights: one safetensors with torchvision's backbone names (`features.{i}.weight|bias`) and
//! the package's head names (`lin{k}.model.1.weight`), as `scripts/convert_eval_weights.py
//! lpips` writes it.

use std::path::Path;

use tch::{Device, Tensor};

use super::WeightFile;
use crate::error::{Error, Result};

/// `lpips.pretrained_networks`' ScalingLayer shift and scale (ImageNet statistics mapped to
/// [-1, 1] inputs).
const SHIFT: [f64; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f64; 3] = [0.458, 0.448, 0.450];
/// `lpips.normalize_tensor`'s epsilon.
const NORM_EPS: f64 = 1e-10;

/// How to make the weight file, for the missing-file message.
pub const HOW_TO_GET: &str = "convert torchvision's backbone (~/.cache/torch/hub/checkpoints/alexnet-owt-7be5be79.pth \
     or vgg16-397923af.pth) and the lpips package's heads (site-packages/lpips/weights/v0.1/alex.pth or vgg.pth) \
     with `scripts/convert_eval_weights.py lpips --net alex --backbone BACKBONE.pth --heads HEADS.pth --out FILE`";

/// The backbone (`alex` or `vgg` in configs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LpipsNet {
    /// torchvision AlexNet (the lpips default and the papers' LPIPS).
    Alex,
    /// torchvision VGG16.
    Vgg,
}

/// One layer of torchvision's `features` Sequential.
#[derive(Debug, Clone, Copy)]
enum Layer {
    /// Conv2d(in, out, kernel, stride, padding) followed by ReLU (index of the conv).
    Conv { index: usize, input: i64, output: i64, kernel: i64, stride: i64, padding: i64 },
    /// MaxPool2d(kernel 3 for AlexNet / 2 for VGG, stride 2).
    Pool { kernel: i64 },
    /// A tap: the preceding ReLU's output is an LPIPS feature.
    Tap,
}

/// torchvision `alexnet().features` with the lpips taps after relu1..relu5.
fn alex_layers() -> Vec<Layer> {
    use Layer::*;
    vec![
        Conv { index: 0, input: 3, output: 64, kernel: 11, stride: 4, padding: 2 },
        Tap,
        Pool { kernel: 3 },
        Conv { index: 3, input: 64, output: 192, kernel: 5, stride: 1, padding: 2 },
        Tap,
        Pool { kernel: 3 },
        Conv { index: 6, input: 192, output: 384, kernel: 3, stride: 1, padding: 1 },
        Tap,
        Conv { index: 8, input: 384, output: 256, kernel: 3, stride: 1, padding: 1 },
        Tap,
        Conv { index: 10, input: 256, output: 256, kernel: 3, stride: 1, padding: 1 },
        Tap,
    ]
}

/// torchvision `vgg16().features` (configuration D) with the lpips taps after relu1_2, relu2_2,
/// relu3_3, relu4_3 and relu5_3.
fn vgg_layers() -> Vec<Layer> {
    let blocks: [&[i64]; 5] = [&[64, 64], &[128, 128], &[256, 256, 256], &[512, 512, 512], &[512, 512, 512]];
    let (mut layers, mut index, mut input) = (Vec::new(), 0, 3);
    for (b, widths) in blocks.iter().enumerate() {
        if b > 0 {
            layers.push(Layer::Pool { kernel: 2 });
            index += 1;
        }
        for &output in widths.iter() {
            layers.push(Layer::Conv { index, input, output, kernel: 3, stride: 1, padding: 1 });
            index += 2;
            input = output;
        }
        layers.push(Layer::Tap);
    }
    layers
}

#[derive(Debug)]
enum Op {
    Conv { weight: Tensor, bias: Tensor, stride: i64, padding: i64 },
    Pool { kernel: i64 },
    Tap,
}

/// A loaded LPIPS model.
#[derive(Debug)]
pub struct Lpips {
    ops: Vec<Op>,
    heads: Vec<Tensor>,
    shift: Tensor,
    scale: Tensor,
}

impl Lpips {
    /// Loads `path`, checking every tensor's name and shape against `net`.
    pub fn load(path: &Path, net: LpipsNet, device: Device) -> Result<Self> {
        let file = WeightFile::open(path, device, "LPIPS", HOW_TO_GET)?;
        let layers = match net {
            LpipsNet::Alex => alex_layers(),
            LpipsNet::Vgg => vgg_layers(),
        };
        let mut ops = Vec::new();
        let mut heads = Vec::new();
        let mut channels = 0;
        for layer in layers {
            ops.push(match layer {
                Layer::Conv { index, input, output, kernel, stride, padding } => {
                    channels = output;
                    Op::Conv {
                        weight: file.get(&format!("features.{index}.weight"), &[output, input, kernel, kernel])?,
                        bias: file.get(&format!("features.{index}.bias"), &[output])?,
                        stride,
                        padding,
                    }
                }
                Layer::Pool { kernel } => Op::Pool { kernel },
                Layer::Tap => {
                    heads.push(file.get(&format!("lin{}.model.1.weight", heads.len()), &[1, channels, 1, 1])?);
                    Op::Tap
                }
            });
        }
        let column =
            |v: [f64; 3]| Tensor::from_slice(&v).to_kind(tch::Kind::Float).view([1, 3, 1, 1]).to_device(device);
        Ok(Self { ops, heads, shift: column(SHIFT), scale: column(SCALE) })
    }

    fn taps(&self, x: &Tensor) -> Result<Vec<Tensor>> {
        let mut x = (x - &self.shift) / &self.scale;
        let mut taps = Vec::new();
        for op in &self.ops {
            match op {
                Op::Conv { weight, bias, stride, padding } => {
                    x = x.f_conv2d(weight, Some(bias), [*stride], [*padding], [1], 1)?.relu();
                }
                Op::Pool { kernel } => x = x.f_max_pool2d([*kernel], [2], [0], [1], false)?,
                Op::Tap => {
                    let norm = x.square().sum_dim_intlist(1, true, None).sqrt() + NORM_EPS;
                    taps.push(&x / norm);
                }
            }
        }
        Ok(taps)
    }

    fn check(x0: &Tensor, x1: &Tensor) -> Result<()> {
        let (a, b) = (x0.size(), x1.size());
        if a.len() != 4 || a[1] != 3 || a != b {
            return Err(Error::Shape {
                tensor: "lpips input".to_string(),
                expected: format!("two equal [N, 3, H, W] tensors (the other is {b:?})"),
                actual: a,
            });
        }
        Ok(())
    }

    /// Per-image LPIPS `[N]` of two `[N, 3, H, W]` batches in [-1, 1].
    pub fn distance(&self, x0: &Tensor, x1: &Tensor) -> Result<Tensor> {
        Self::check(x0, x1)?;
        let (t0, t1) = (self.taps(x0)?, self.taps(x1)?);
        let mut total = Tensor::zeros([x0.size()[0]], (tch::Kind::Float, x0.device()));
        for ((a, b), head) in t0.iter().zip(&t1).zip(&self.heads) {
            let d = (a - b).square().f_conv2d(head, None::<Tensor>, [1], [0], [1], 1)?;
            total += d.mean_dim([1, 2, 3].as_slice(), false, None);
        }
        Ok(total)
    }

    /// The LPIPS map `[N, H, W]` (`spatial=True`): each tap's weighted distance upsampled
    /// bilinearly (align_corners false) to the input size, summed.
    pub fn spatial(&self, x0: &Tensor, x1: &Tensor) -> Result<Tensor> {
        Self::check(x0, x1)?;
        let size = x0.size();
        let (t0, t1) = (self.taps(x0)?, self.taps(x1)?);
        let mut total = Tensor::zeros([size[0], size[2], size[3]], (tch::Kind::Float, x0.device()));
        for ((a, b), head) in t0.iter().zip(&t1).zip(&self.heads) {
            let d = (a - b).square().f_conv2d(head, None::<Tensor>, [1], [0], [1], 1)?;
            total += d.f_upsample_bilinear2d([size[2], size[3]], false, None, None)?.squeeze_dim(1);
        }
        Ok(total)
    }
}

/// `[N, 3, H, W]` in [-1, 1] (`lpips.im2tensor`) from RGB frames of one size.
pub fn frames_to_input(frames: &[&image::RgbImage], device: Device) -> Tensor {
    super::frames_to_tensor(frames, 2.0, -1.0, device)
}
