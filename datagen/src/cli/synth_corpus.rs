//! `datagen synth-corpus`: a small corpus of synthetic videos in every dataset layout
//! ([`crate::corpus::synthetic`]).

use std::path::PathBuf;

use clap::Args;

use crate::synth::SynthConfig;

/// Arguments of `datagen synth-corpus`.
#[derive(Debug, Args)]
pub struct SynthCorpusArgs {
    /// Root folder of the generated trees.
    #[arg(long)]
    pub out: PathBuf,
    /// Videos per dataset layout.
    #[arg(long, default_value_t = 2)]
    pub videos_per_layout: usize,
    /// Synth scene settings (TOML, as for `datagen synth --config`); default: 320x192, 25 frames.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output folder written into the corpus.toml [default: <OUT>/corpus].
    #[arg(long)]
    pub corpus_out: Option<PathBuf>,
}

/// Runs `datagen synth-corpus`.
pub fn run(args: SynthCorpusArgs) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => crate::config_file::load_toml(path)?,
        None => SynthConfig::default(),
    };
    let out = args.corpus_out.unwrap_or_else(|| args.out.join("corpus"));
    let corpus = crate::corpus::synthetic::write_synthetic_corpus(&args.out, &out, args.videos_per_layout, &config)?;
    println!(
        "wrote {} videos in each of 5 layouts under {}; build them with: datagen build --config {}",
        corpus.videos_per_layout,
        args.out.display(),
        corpus.config.display()
    );
    Ok(())
}
