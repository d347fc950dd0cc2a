//! The learning-rate schedule: linear warm-up, then constant or cosine decay to 0 at the last
//! step.

use super::OptimConfig;

/// The learning rate at optimizer step `step` (0-based).
pub fn learning_rate(config: &OptimConfig, step: u64, total_steps: u64) -> f64 {
    if step < config.warmup_steps {
        return config.lr * (step + 1) as f64 / config.warmup_steps as f64;
    }
    match config.schedule.as_str() {
        "cosine" => {
            let span = total_steps.saturating_sub(config.warmup_steps).max(1) as f64;
            let progress = (step - config.warmup_steps) as f64 / span;
            config.lr * 0.5 * (1.0 + (std::f64::consts::PI * progress.min(1.0)).cos())
        }
        _ => config.lr,
    }
}
