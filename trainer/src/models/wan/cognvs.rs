//! The CogNVS conditioning on Wan: the hole mask brought onto the latent grid as the
//! image-to-video transformers' mask channels, as `WanImageToVideoPipeline.prepare_latents`
//! builds them for "the first frame is known" (here: the pixels the render knows). Used by
//! sampling (`pipelines::pipeline_wan`) and training (through `models::backbone`).

use tch::{Kind, Tensor};

use crate::error::{Error, Result};

/// The mask channels `[B, t, F', h, w]` of a mask `[B, 1, F, H, W]` (1 known, F = 1 + t·(F' −
/// 1)): known only where every pixel of the s × s block is (a minimum over the block), the first
/// frame repeated t times so that the F + t − 1 frames fold into t channels per latent frame.
pub fn mask_channels(mask: &Tensor, temporal: i64, spatial: i64) -> Result<Tensor> {
    let size = mask.size();
    let frames = match size[..] {
        [_, 1, f, h, w] if f >= 1 && (f - 1) % temporal == 0 && h % spatial == 0 && w % spatial == 0 => f,
        _ => {
            return Err(Error::Shape {
                tensor: "condition mask".to_string(),
                expected: format!("[B, 1, 1 + {temporal}k, H, W] with H and W multiples of {spatial}"),
                actual: size,
            });
        }
    };
    // A minimum, as −max(−m).
    let mask = mask
        .f_to_kind(Kind::Float)?
        .f_neg()?
        .f_max_pool3d([1, spatial, spatial], [1, spatial, spatial], [0, 0, 0], [1, 1, 1], false)?
        .f_neg()?;
    let first = mask.f_narrow(2, 0, 1)?.f_repeat([1, 1, temporal, 1, 1])?;
    let mask = Tensor::f_cat(&[first, mask.f_narrow(2, 1, frames - 1)?], 2)?;
    let [b, _, _, h, w] = mask.size()[..] else { unreachable!("5-D mask") };
    Ok(mask.f_view([b, -1, temporal, h, w])?.f_transpose(1, 2)?.f_contiguous()?)
}
