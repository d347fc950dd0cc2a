//! A clip: the window of a video that becomes one training record ([`ClipConfig`]), and the
//! pivot distance R that every novel path of the clip orbits about or is scaled by
//! ([`pivot_distance`]). Both the pair generator and the trajectory bank cut videos this way.

use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_count};
use foundation::camera::PinholeCamera;
use foundation::depth::DepthMap;

/// Paper value: the CogNVS paper trains on clips of 49 frames.
pub const PAPER_CLIP_FRAMES: u32 = 49;

/// How a video is cut into clips.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ClipConfig {
    /// Frames per clip; shorter videos are kept whole as one clip. Valid: at least 1.
    pub length: u32,
    /// Frames between the starts of consecutive clips (equal to `length`: back to back).
    /// Valid: at least 1.
    pub stride: u32,
    /// At most this many clips per video (0: all). Valid: any.
    pub max_clips: u32,
}

impl Validate for ClipConfig {
    fn validate(&self) -> Checked {
        check_count("length", self.length, 1, u64::MAX)?;
        check_count("stride", self.stride, 1, u64::MAX)
    }
}

impl Default for ClipConfig {
    fn default() -> Self {
        Self { length: PAPER_CLIP_FRAMES, stride: PAPER_CLIP_FRAMES, max_clips: 0 }
    }
}

impl ClipConfig {
    /// Start frames of the clips of a video of `frames` frames, and the clip length used.
    pub fn windows(&self, frames: u32) -> Vec<(u32, u32)> {
        if frames <= self.length {
            return vec![(0, frames)];
        }
        let mut starts: Vec<(u32, u32)> =
            (0..=frames - self.length).step_by(self.stride.max(1) as usize).map(|s| (s, self.length)).collect();
        if self.max_clips > 0 {
            starts.truncate(self.max_clips as usize);
        }
        starts
    }
}

/// Half-size of the window around the optical centre whose median valid depth gives R.
const PIVOT_WINDOW: i64 = 2;

/// R: the median valid depth in a small window around the first frame's principal point (the
/// whole frame's median if that window has none), × `scale`.
pub fn pivot_distance(depth: &DepthMap, camera: &PinholeCamera, scale: f64) -> f64 {
    let (cx, cy) = (camera.intrinsics.z_axis.x.round() as i64, camera.intrinsics.z_axis.y.round() as i64);
    let valid = |d: f32| d.is_finite() && d > 0.0;
    let mut window: Vec<f32> = Vec::new();
    for v in cy - PIVOT_WINDOW..=cy + PIVOT_WINDOW {
        for u in cx - PIVOT_WINDOW..=cx + PIVOT_WINDOW {
            if u >= 0 && v >= 0 && (u as usize) < depth.width && (v as usize) < depth.height {
                let d = depth.values[v as usize * depth.width + u as usize];
                if valid(d) {
                    window.push(d);
                }
            }
        }
    }
    if window.is_empty() {
        window = depth.values.iter().copied().filter(|&d| valid(d)).collect();
    }
    window.sort_by(f32::total_cmp);
    scale * f64::from(window.get(window.len() / 2).copied().unwrap_or(1.0))
}
