//! Evaluation as the paper reports it (CogNVS §5, its Tables 1–3 and the appendix's top-k
//! ablation): LPIPS as the `lpips` package computes it, FID and KID as `clean-fid` computes
//! them, and `score`: the table over folders of predicted and target videos. PSNR/SSIM live in
//! [`crate::eval::metrics`] (scikit-image conventions).
//!
//! Network weights come from files users already have, converted once by
//! `scripts/convert_eval_weights.py`; nothing is downloaded.

pub mod fid;
pub mod inception;
pub mod lpips;
pub mod metrics;
pub mod resize;
pub mod score;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};

/// The tensors of one converted weight file, handed out by name with their shapes checked, so a
/// wrong or truncated file fails naming the file, the tensor and both shapes.
#[derive(Debug)]
pub struct WeightFile {
    path: PathBuf,
    tensors: BTreeMap<String, Tensor>,
    device: Device,
}

impl WeightFile {
    /// Reads `path` (safetensors). `what` and `how` make the message when the file is missing:
    /// which metric needs it and how to produce it.
    pub fn open(path: &Path, device: Device, what: &str, how: &str) -> Result<Self> {
        if !path.is_file() {
            return Err(Error::InvalidInput {
                path: path.to_path_buf(),
                what: format!("{what} weights"),
                reason: format!("no such file; {how}"),
            });
        }
        let tensors = crate::models::weights::read_safetensors(path)?;
        Ok(Self { path: path.to_path_buf(), tensors, device })
    }

    /// The tensor `name` as f32 on the device, checked to have `shape`.
    pub fn get(&self, name: &str, shape: &[i64]) -> Result<Tensor> {
        let tensor = self.tensors.get(name).ok_or_else(|| Error::MissingTensor {
            path: self.path.clone(),
            tensor: name.to_string(),
            expected: shape.to_vec(),
        })?;
        if tensor.size() != shape {
            return Err(Error::Shape {
                tensor: format!("{name}` in `{}", self.path.display()),
                expected: format!("{shape:?}"),
                actual: tensor.size(),
            });
        }
        crate::models::weights::check_floating(&self.path, name, tensor)?;
        Ok(tensor.to_kind(Kind::Float).to_device(self.device))
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// `[N, 3, H, W]` f32 with values `v / 255 · scale + offset` from RGB u8 frames of one size.
pub(crate) fn frames_to_tensor(frames: &[&image::RgbImage], scale: f64, offset: f64, device: Device) -> Tensor {
    let (w, h) = frames[0].dimensions();
    let data: Vec<u8> = frames.iter().flat_map(|f| f.as_raw().iter().copied()).collect();
    Tensor::from_slice(&data)
        .view([frames.len() as i64, h as i64, w as i64, 3])
        .permute([0, 3, 1, 2])
        .to_kind(Kind::Float)
        .to_device(device)
        * (scale / 255.0)
        + offset
}
