//! VAE parity with diffusers (encode, decode, tiled, single frame), exact key paths, bf16, and
//! temporally batched (streaming) encoding against a single pass.
//!
//! Reference values come from `scripts/goldens_vae_scheduler.py` (diffusers'
//! `AutoencoderKLCogVideoX` with a fixed seed), run into a temporary folder once per test binary.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::sync::OnceLock;

use trainer::diffusers_config::DiffusersConfig;
use trainer::models::cogvideox::autoencoder_kl_cogvideox::{
    self as vae, AutoencoderKLCogVideoX, AutoencoderKLCogVideoXConfig, TilingConfig,
};
use trainer::tch::{self, Device, Kind, Tensor, nn};

use super::parity::{assert_close, errors, read_tensors, run_script};

/// Output of `scripts/goldens_vae_scheduler.py`, generated once per test binary.
pub fn goldens() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| run_script("goldens_vae_scheduler.py")).path()
}

/// The tiny VAE with diffusers' weights loaded (names and shapes checked both ways).
fn tiny_vae() -> (nn::VarStore, AutoencoderKLCogVideoX) {
    let dir = goldens().join("vae");
    let config = AutoencoderKLCogVideoXConfig::from_json_file(&dir).unwrap();
    assert_eq!(
        AutoencoderKLCogVideoXConfig { extra: Default::default(), ..config.clone() },
        AutoencoderKLCogVideoXConfig::tiny(),
        "the script's TINY_VAE and the Rust `tiny` preset must agree"
    );
    let mut vs = nn::VarStore::new(Device::Cpu);
    let model = AutoencoderKLCogVideoX::new(&vs.root(), &config).unwrap();
    load_checked(&mut vs, &dir.join("diffusion_pytorch_model.safetensors"));
    (vs, model)
}

fn load_checked(vs: &mut nn::VarStore, path: &Path) {
    let file = read_tensors(path);
    let vars = vs.variables();
    let ours: BTreeSet<&String> = vars.keys().collect();
    let theirs: BTreeSet<&String> = file.keys().collect();
    assert_eq!(ours, theirs, "variable names must equal diffusers' state-dict keys");
    tch::no_grad(|| {
        for (name, mut var) in vars {
            let src = &file[&name];
            assert_eq!(var.size(), src.size(), "{name}");
            var.copy_(src);
        }
    });
}

#[test]
fn encode_matches_diffusers() {
    let (_vs, model) = tiny_vae();
    let io = read_tensors(&goldens().join("vae_io.safetensors"));
    let latent = tch::no_grad(|| model.encode(&io["encode.sample"])).unwrap();
    assert_close("vae encode (17 frames, 9+8 batches)", &latent, &io["encode.latent"], 1e-4);
    let latent1 = tch::no_grad(|| model.encode(&io["encode1.sample"])).unwrap();
    assert_close("vae encode (1 frame, batch 2)", &latent1, &io["encode1.latent"], 1e-4);
}

#[test]
fn decode_matches_diffusers() {
    let (_vs, model) = tiny_vae();
    let io = read_tensors(&goldens().join("vae_io.safetensors"));
    let sample = tch::no_grad(|| model.decode(&io["decode.latent"])).unwrap();
    assert_close("vae decode (5 latent frames, 3+2 batches)", &sample, &io["decode.sample"], 1e-4);
    let sample1 = tch::no_grad(|| model.decode(&io["decode1.latent"])).unwrap();
    assert_close("vae decode (1 latent frame, batch 2)", &sample1, &io["decode1.sample"], 1e-4);
}

#[test]
fn tiled_encode_and_decode_match_diffusers() {
    let (_vs, mut model) = tiny_vae();
    let io = read_tensors(&goldens().join("vae_io.safetensors"));
    let json = std::fs::read_to_string(goldens().join("vae_tiling.json")).unwrap();
    let tiling: TilingConfig = serde_json::from_str(&json).unwrap();
    model.enable_tiling(tiling).unwrap();
    let latent = tch::no_grad(|| model.encode(&io["tiled_encode.sample"])).unwrap();
    assert_close("vae tiled encode (64x80, 2x3 tiles)", &latent, &io["tiled_encode.latent"], 1e-4);
    let sample = tch::no_grad(|| model.decode(&io["tiled_decode.latent"])).unwrap();
    assert_close("vae tiled decode (8x10 latent, 2x3 tiles)", &sample, &io["tiled_decode.sample"], 1e-4);
}

#[test]
fn bf16_tracks_fp32() {
    let (mut vs, model) = tiny_vae();
    let io = read_tensors(&goldens().join("vae_io.safetensors"));
    vs.bfloat16();
    let latent = tch::no_grad(|| model.encode(&io["encode.sample"].to_kind(Kind::BFloat16))).unwrap();
    assert_eq!(latent.kind(), Kind::BFloat16);
    // bf16 keeps 8 bits of mantissa; through ~20 layers a few percent is expected.
    assert_close("vae encode bf16 vs diffusers fp32", &latent, &io["encode.latent"], 5e-2);
    let sample = tch::no_grad(|| model.decode(&io["decode.latent"].to_kind(Kind::BFloat16))).unwrap();
    assert_close("vae decode bf16 vs diffusers fp32", &sample, &io["decode.sample"], 5e-2);
}

#[test]
fn streaming_encode_equals_batched_encode() {
    // The public stream API, fed diffusers' temporal batches, reproduces `encode` bit for bit.
    let (_vs, model) = tiny_vae();
    let io = read_tensors(&goldens().join("vae_io.safetensors"));
    let x = &io["encode.sample"];
    let expected = tch::no_grad(|| model.encode(x)).unwrap();
    let mut stream = model.encoder_stream();
    let parts: Vec<Tensor> = vae::temporal_batches(17, vae::SAMPLE_FRAMES_BATCH_SIZE)
        .into_iter()
        .map(|(s, n)| tch::no_grad(|| stream.push(&x.narrow(2, s, n))).unwrap())
        .collect();
    let streamed = Tensor::cat(&parts, 2);
    assert_eq!(errors(&streamed, &expected).0, 0.0);
}

/// Relative error of each latent frame of `a` against `b`.
fn per_frame_errors(a: &Tensor, b: &Tensor) -> Vec<f64> {
    (0..a.size()[2]).map(|f| errors(&a.narrow(2, f, 1), &b.narrow(2, f, 1)).1).collect()
}

#[test]
fn chunked_encode_is_close_to_one_pass() {
    // Streaming must equal the whole-clip pass, as far as this VAE allows. The causal convolutions
    // stream exactly (unit test `causal_conv_streams_exactly`); between temporal batches and one
    // pass over all frames only GroupNorm's statistics differ (they span a batch's frames), which
    // shifts the latent frames of every batch alike. A lost conv cache instead makes every later
    // batch (latent frames 3.. here) much worse than the first. Checked on two 25-frame clips
    // (batches of 9 + 8 + 8 → 7 latent frames): temporally smooth (a fixed frame plus 10 % noise,
    // like video) and i.i.d. noise (the worst case for GroupNorm statistics).
    let (_vs, model) = tiny_vae();
    tch::manual_seed(7);
    let opts = (Kind::Float, Device::Cpu);
    let base = Tensor::rand([1, 3, 1, 32, 48], opts) * 1.6 - 0.8;
    let smooth = base.repeat([1, 1, 25, 1, 1]) + Tensor::randn([1, 3, 25, 32, 48], opts) * 0.1;
    let noise = Tensor::rand([1, 3, 25, 32, 48], opts) * 2.0 - 1.0;
    let later_over_first = |errs: &[f64]| {
        let first = errs[..3].iter().copied().fold(0.0, f64::max);
        errs[3..].iter().copied().fold(0.0, f64::max) / first
    };
    for (name, x) in [("smooth", &smooth), ("noise", &noise)] {
        let chunked = tch::no_grad(|| model.encode(x)).unwrap();
        let whole = tch::no_grad(|| model.encode_whole(x)).unwrap();
        assert_eq!(chunked.size(), [1, 16, 7, 4, 6]);
        let no_cache = tch::no_grad(|| {
            let parts: Vec<Tensor> = vae::temporal_batches(25, vae::SAMPLE_FRAMES_BATCH_SIZE)
                .into_iter()
                .map(|(s, n)| model.encoder_stream().push(&x.narrow(2, s, n)).unwrap())
                .collect();
            Tensor::cat(&parts, 2)
        });
        let good = per_frame_errors(&chunked, &whole);
        let broken = per_frame_errors(&no_cache, &whole);
        let (abs, rel) = errors(&chunked, &whole);
        println!("chunked vs one pass, {name} clip: max abs {abs:.3e}, rel {rel:.3e}");
        println!("  per latent frame, with cache:    {good:.3?}");
        println!("  per latent frame, without cache: {broken:.3?}");
        assert!(later_over_first(&good) < 2.0, "{name}: later batches drift: {good:.3?}");
        assert!(later_over_first(&broken) > 2.0, "{name}: the check cannot see a lost cache: {broken:.3?}");
        if name == "smooth" {
            assert!(rel < 5e-2, "smooth clip: chunked vs one-pass relative error {rel:.3e}");
        }
    }
}

#[test]
fn module_tree_of_the_5b_vae_matches_diffusers() {
    // Every variable of the real CogVideoX-5B VAE at diffusers' key with diffusers' shape, nothing
    // missing, nothing extra (diffusers' names/shapes dumped from a meta-device model).
    let json = std::fs::read_to_string(goldens().join("vae_5b_shapes.json")).unwrap();
    let expected: BTreeMap<String, Vec<i64>> = serde_json::from_str(&json).unwrap();
    let vs = nn::VarStore::new(Device::Cpu);
    let _model = AutoencoderKLCogVideoX::new(&vs.root(), &AutoencoderKLCogVideoXConfig::cogvideox_5b()).unwrap();
    let ours: BTreeMap<String, Vec<i64>> = vs.variables().into_iter().map(|(k, v)| (k, v.size())).collect();
    let missing: Vec<_> = expected.keys().filter(|k| !ours.contains_key(*k)).collect();
    let extra: Vec<_> = ours.keys().filter(|k| !expected.contains_key(*k)).collect();
    assert!(missing.is_empty() && extra.is_empty(), "missing {missing:?}, extra {extra:?}");
    for (key, shape) in &expected {
        assert_eq!(&ours[key], shape, "{key}");
    }
    let params: i64 = ours.values().map(|s| s.iter().product::<i64>()).sum();
    println!("5B VAE: {} tensors, {params} parameters", ours.len());
}
