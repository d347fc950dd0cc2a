//! `datagen inspect`: statistics of a shard or corpus, exports and the HTML report
//! ([`crate::inspect`]).

use std::path::PathBuf;

use clap::Args;

/// Arguments of `datagen inspect`.
#[derive(Debug, Args)]
pub struct InspectArgs {
    /// A shard file or a folder of shards (a corpus).
    pub path: PathBuf,
    /// Write every pair under this folder.
    #[arg(long)]
    pub export: Option<PathBuf>,
    /// With --export: fill the holes of the contact sheet's novel renders from the static
    /// background stacked over each clip's frames.
    #[arg(long)]
    pub stack_background: bool,
    /// With --export: `pairs` (a folder per pair: PNGs, meta.json, contact sheet) or `cog-nvs`
    /// (a folder per clip as the public cog-nvs finetuning code reads it: gt_rgb.mp4 and
    /// train_render{k}.mp4, k from 1).
    #[arg(long, value_enum, default_value_t = ExportLayout::Pairs, requires = "export")]
    pub layout: ExportLayout,
    /// Write a self-contained HTML report (counts, failures by reason, histograms, thumbnails
    /// linked to the --export folders) to this file.
    #[arg(long)]
    pub report: Option<PathBuf>,
}

/// The layout `datagen inspect --export` writes (an output layout, not one the registry reads).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExportLayout {
    /// A folder per pair.
    Pairs,
    /// A folder per clip in the public cog-nvs finetuning layout.
    CogNvs,
}

/// Runs `datagen inspect`.
pub fn run(args: InspectArgs) -> anyhow::Result<()> {
    print!("{}", crate::inspect::shards::report(&args.path)?);
    if let (Some(export), ExportLayout::CogNvs) = (&args.export, args.layout) {
        let folders = crate::inspect::shards::export_cog_nvs(&args.path, export)?;
        println!("exported {} clips in the cog-nvs layout to {}", folders.len(), export.display());
    } else if let Some(export) = &args.export {
        let render = crate::inspect::shards::ExportRender {
            covisibility: Default::default(),
            stacking: args.stack_background.then(Default::default),
        };
        let folders = crate::inspect::shards::export(&args.path, export, Some(&render))?;
        println!("exported {} pairs to {}", folders.len(), export.display());
        if let Some(first) = folders.first() {
            println!("  look at: {}", first.join("contact_sheet.png").display());
        }
    }
    if let Some(out) = &args.report {
        let options = crate::inspect::report::ReportOptions {
            export_dir: args.export.clone().filter(|_| args.layout == ExportLayout::Pairs),
            ..Default::default()
        };
        let summary = crate::inspect::report::write_report(&args.path, out, &options)?;
        println!(
            "wrote {} ({} shards, {} clips, {} pairs, {} thumbnails, {} failed or skipped inputs)",
            out.display(),
            summary.shards,
            summary.clips,
            summary.pairs,
            summary.thumbnails,
            summary.failures
        );
    }
    Ok(())
}
