//! `datagen synth`: a synthetic dynamic scene with exact ground truth ([`crate::synth`]), as one
//! sequence folder or, with `--cameras`, a synchronised multi-camera scene
//! ([`crate::synth_layouts`]).

use std::path::PathBuf;

use clap::Args;

use crate::config_file::Validate;
use crate::synth::{CameraRig, SynthConfig, write_sequence};
use crate::synth_layouts::SynthFormat;

/// Arguments of `datagen synth`.
#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Output sequence folder (created if missing).
    #[arg(long, default_value = "out/synth")]
    pub out: PathBuf,
    /// TOML file with any of the fields below (flags given on the command line win).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Frame width in pixels (even) [default: 320].
    #[arg(long)]
    pub width: Option<u32>,
    /// Frame height in pixels (even) [default: 192].
    #[arg(long)]
    pub height: Option<u32>,
    /// Number of frames [default: 25].
    #[arg(long)]
    pub frames: Option<u32>,
    /// Frame rate of the written video [default: 24].
    #[arg(long)]
    pub fps: Option<f64>,
    /// Number of moving objects (spheres and boxes) [default: 3].
    #[arg(long)]
    pub moving_objects: Option<u32>,
    /// Number of static boxes [default: 3].
    #[arg(long)]
    pub static_objects: Option<u32>,
    /// Number of thin static objects: poles and plates a few centimetres thick [default: 0].
    #[arg(long)]
    pub thin_objects: Option<u32>,
    /// Seed of every random choice [default: 0].
    #[arg(long)]
    pub seed: Option<u64>,
    /// Render the scene from this many synchronised cameras (2 to 64) instead of one: OUT/camNN/
    /// per camera in the generic layout (frames/, depth/*.exr, cameras.json with timestamps).
    #[arg(long)]
    pub cameras: Option<u32>,
    /// With --cameras: yaw between neighbouring cameras about the scene's centre, in degrees.
    #[arg(long, default_value_t = 10.0, requires = "cameras")]
    pub camera_spacing_deg: f64,
    /// With --cameras: the layout to write: generic (camNN/ sequence folders), dycheck (DyCheck
    /// iPhone: camera 0 moving with depth, the others static and held out) or kubric4d (Kubric-4D
    /// as GCD ships it; OUT's name is the scene id).
    #[arg(long, default_value = "generic", requires = "cameras")]
    pub format: SynthFormat,
}

impl SynthArgs {
    /// The scene settings: the `--config` file (or the defaults) with the flags given on top,
    /// checked.
    pub fn config(&self) -> anyhow::Result<SynthConfig> {
        let mut config = match &self.config {
            Some(path) => crate::config_file::load_toml(path)?,
            None => SynthConfig::default(),
        };
        let overrides = [
            (self.width, &mut config.width),
            (self.height, &mut config.height),
            (self.frames, &mut config.frames),
            (self.moving_objects, &mut config.moving_objects),
            (self.static_objects, &mut config.static_objects),
            (self.thin_objects, &mut config.thin_objects),
        ];
        for (value, field) in overrides {
            if let Some(value) = value {
                *field = value;
            }
        }
        config.fps = self.fps.unwrap_or(config.fps);
        config.seed = self.seed.unwrap_or(config.seed);
        config.validate()?;
        Ok(config)
    }

    /// The camera rig of a multi-camera scene (`--cameras`), if one was asked for.
    pub fn rig(&self) -> Option<CameraRig> {
        self.cameras.map(|cameras| CameraRig { cameras, spacing_deg: self.camera_spacing_deg })
    }
}

/// Runs `datagen synth`.
pub fn run(args: SynthArgs) -> anyhow::Result<()> {
    let config = args.config()?;
    let bar = indicatif::ProgressBar::new(config.frames as u64).with_style(
        indicatif::ProgressStyle::with_template("rendering {bar:30} {pos}/{len} frames [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    );
    if let Some(rig) = args.rig() {
        let progress = |done| bar.set_position(done as u64);
        crate::synth_layouts::write_multiview_as(&config, &rig, args.format, &args.out, progress)?;
        bar.finish_and_clear();
        let layout = match args.format {
            SynthFormat::Generic => "camNN/: frames/, depth/, cameras.json",
            SynthFormat::Dycheck => "DyCheck layout: camera/, rgb/, depth/, covisible/, splits/",
            SynthFormat::Kubric4d => "Kubric-4D layout: frames_p0_vN/, <scene>_p0_vN.json",
        };
        println!(
            "wrote a {}x{} scene of {} frames from {} synchronised cameras to {} ({layout})",
            config.width,
            config.height,
            config.frames,
            rig.cameras,
            args.out.display()
        );
        return Ok(());
    }
    let output = write_sequence(&config, &args.out, |done| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    println!(
        "wrote a {}x{} scene of {} frames to {}\n  video:  {}\n  cameras and depth: {}\n  moving-object masks: {}\n  look at: {}",
        config.width,
        config.height,
        config.frames,
        output.dir.display(),
        output.dir.join("gt_rgb.mp4").display(),
        output.dir.join("cam_info").display(),
        output.dir.join("masks").display(),
        output.contact_sheet.display(),
    );
    Ok(())
}
