//! Scheduler parity with diffusers: ᾱ_t, timesteps, add_noise, get_velocity, and full 50-step
//! CogVideoXDPMScheduler / CogVideoXDDIMScheduler loops on the CogVideoX-5B configuration.
//!
//! Reference values come from `scripts/goldens_vae_scheduler.py` (see `vae.rs`'s `goldens`).

use trainer::diffusers_config::DiffusersConfig;
use trainer::schedulers::{CogVideoXDDIMScheduler, CogVideoXSchedulerConfig};
use trainer::schedulers::{CogVideoXDPMScheduler, Scheduler};
use trainer::tch::Tensor;

use super::parity::{assert_close, read_tensors};
use super::vae::goldens;

fn config() -> CogVideoXSchedulerConfig {
    let config = CogVideoXSchedulerConfig::from_json_file(goldens().join("scheduler")).unwrap();
    assert_eq!(
        CogVideoXSchedulerConfig { extra: Default::default(), ..config.clone() },
        CogVideoXSchedulerConfig::cogvideox_5b(),
        "the script's SCHEDULER_5B and the Rust preset must agree"
    );
    config
}

#[test]
fn schedule_and_timesteps_match_diffusers() {
    let io = read_tensors(&goldens().join("scheduler_io.safetensors"));
    let mut dpm = CogVideoXDPMScheduler::new(&config()).unwrap();
    let ours = Tensor::from_slice(dpm.schedule().alphas_cumprod());
    assert_close("alphas_cumprod (f64)", &ours, &io["alphas_cumprod"], 1e-12);
    for steps in [50usize, 7] {
        dpm.set_timesteps(steps).unwrap();
        let expected: Vec<i64> = Vec::try_from(&io[&format!("set_timesteps.{steps}")]).unwrap();
        assert_eq!(dpm.timesteps(), expected.as_slice(), "set_timesteps({steps})");
    }
}

#[test]
fn add_noise_and_velocity_match_diffusers() {
    let io = read_tensors(&goldens().join("scheduler_io.safetensors"));
    let dpm = CogVideoXDPMScheduler::new(&config()).unwrap();
    let (x0, noise, t) = (&io["add_noise.original_samples"], &io["add_noise.noise"], &io["add_noise.timesteps"]);
    assert_close("add_noise", &dpm.add_noise(x0, noise, t).unwrap(), &io["add_noise.noisy_samples"], 1e-6);
    assert_close("get_velocity", &dpm.get_velocity(x0, noise, t).unwrap(), &io["get_velocity.velocity"], 1e-6);
    // A timestep per sample is required: a wrong count is a named error.
    let bad = Tensor::from_slice(&[1i64, 2]);
    let err = dpm.add_noise(x0, noise, &bad).unwrap_err().to_string();
    assert!(err.contains("timesteps"), "{err}");
}

#[test]
fn dpm_loop_matches_diffusers() {
    let io = read_tensors(&goldens().join("scheduler_io.safetensors"));
    let mut dpm = CogVideoXDPMScheduler::new(&config()).unwrap();
    dpm.set_timesteps(50).unwrap();
    let timesteps = dpm.timesteps().to_vec();
    let mut sample = io["dpm.initial_sample"].shallow_clone();
    let mut old_pred: Option<Tensor> = None;
    let mut worst = 0.0f64;
    for (i, &t) in timesteps.iter().enumerate() {
        let back = (i > 0).then(|| timesteps[i - 1]);
        let out = dpm
            .step_with_noise(
                &io[&format!("dpm.{i}.model_output")],
                old_pred.as_ref(),
                t,
                back,
                &sample,
                &io[&format!("dpm.{i}.noise")],
            )
            .unwrap();
        let (_, rel) = super::parity::errors(&out.prev_sample, &io[&format!("dpm.{i}.prev_sample")]);
        worst = worst.max(rel);
        assert_close(
            &format!("dpm step {i} (t={t}) x0"),
            &out.pred_original_sample,
            &io[&format!("dpm.{i}.pred_original_sample")],
            1e-4,
        );
        // Feed diffusers' own outputs forward so each step is checked on its own.
        sample = io[&format!("dpm.{i}.prev_sample")].shallow_clone();
        old_pred = Some(io[&format!("dpm.{i}.pred_original_sample")].shallow_clone());
    }
    println!("parity dpm 50 steps: worst prev_sample rel {worst:.3e}");
    assert!(worst <= 1e-4, "worst DPM step relative error {worst:.3e}");
}

#[test]
fn ddim_loop_matches_diffusers() {
    let io = read_tensors(&goldens().join("scheduler_io.safetensors"));
    let mut ddim = CogVideoXDDIMScheduler::new(&config()).unwrap();
    ddim.set_timesteps(50).unwrap();
    let timesteps = ddim.timesteps().to_vec();
    // Chained: our own sample carried through all 50 steps.
    let mut sample = io["ddim.initial_sample"].shallow_clone();
    for (i, &t) in timesteps.iter().enumerate() {
        let out = ddim.step(&io[&format!("ddim.{i}.model_output")], t, &sample).unwrap();
        sample = out.prev_sample;
    }
    assert_close("ddim 50 chained steps", &sample, &io["ddim.49.prev_sample"], 1e-4);
}
