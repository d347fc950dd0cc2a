//! Shared helpers of the parity tests: running the golden scripts of `scripts/` (diffusers in the
//! project venv), comparing tensors, and writing tiny random models in the diffusers layout.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use trainer::tch::{Device, Kind, Tensor};

/// The project venv's Python (`.venv/bin/python`, or `$TRAINER_PYTHON`).
pub fn python() -> PathBuf {
    std::env::var_os("TRAINER_PYTHON").map(PathBuf::from).unwrap_or_else(|| repo_root().join(".venv/bin/python"))
}

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Runs `scripts/<script> <args…>` with the venv's Python, panicking with its status on failure.
pub fn run_python(script: &str, args: &[&std::ffi::OsStr]) {
    let python = python();
    let status = std::process::Command::new(&python)
        .arg(repo_root().join("scripts").join(script))
        .args(args)
        .status()
        .unwrap_or_else(|e| panic!("cannot run {}: {e} (run scripts/setup.sh)", python.display()));
    assert!(status.success(), "scripts/{script} failed: {status}");
}

/// Runs a golden script (`scripts/<script> OUT_DIR`) into a fresh temporary folder.
pub fn run_script(script: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("temp dir");
    run_python(script, &[dir.path().as_os_str()]);
    dir
}

/// Named tensors of a safetensors file.
/// Asserts that a finished command exited 0, showing its stdout and stderr when it did not.
pub fn assert_success(output: &std::process::Output) {
    assert!(
        output.status.success(),
        "command failed: {}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
}

pub fn read_tensors(path: &Path) -> BTreeMap<String, Tensor> {
    Tensor::read_safetensors(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).into_iter().collect()
}

/// Max absolute error and max error relative to the reference's largest magnitude.
pub fn errors(actual: &Tensor, expected: &Tensor) -> (f64, f64) {
    assert_eq!(actual.size(), expected.size(), "shape");
    let a = actual.to_kind(Kind::Double).to_device(Device::Cpu);
    let e = expected.to_kind(Kind::Double);
    let abs = (&a - &e).abs().max().double_value(&[]);
    let scale = e.abs().max().double_value(&[]).max(1e-12);
    (abs, abs / scale)
}

/// Asserts relative error ≤ `tol` and prints the figures (reported in the parity table).
pub fn assert_close(name: &str, actual: &Tensor, expected: &Tensor, tol: f64) {
    let (abs, rel) = errors(actual, expected);
    println!("parity {name}: max abs {abs:.3e}, rel {rel:.3e}");
    assert!(rel <= tol, "{name}: max abs error {abs:.3e}, relative {rel:.3e} > {tol:.0e}");
}

/// Writes a random transformer of `config` to `transformer_dir` and a tiny random VAE to `vae_dir`,
/// in the diffusers layout `trainer` reads.
pub fn save_tiny_models(
    config: &trainer::models::cogvideox::cogvideox_transformer_3d::CogVideoXTransformer3DModelConfig,
    transformer_dir: &Path,
    vae_dir: &Path,
) {
    use trainer::models::cogvideox::{autoencoder_kl_cogvideox as vae, cogvideox_transformer_3d as transformer};
    use trainer::models::weights;
    let max = weights::DEFAULT_MAX_SHARD_BYTES;
    let (vs, _model) = transformer::build(config, Device::Cpu, Kind::Float).unwrap();
    weights::save(&vs, config, transformer::CLASS_NAME, transformer_dir, max).unwrap();
    let vae_config = vae::AutoencoderKLCogVideoXConfig::tiny();
    let (vae_vs, _vae) = vae::build(&vae_config, Device::Cpu, Kind::Float).unwrap();
    weights::save(&vae_vs, &vae_config, vae::CLASS_NAME, vae_dir, max).unwrap();
}
