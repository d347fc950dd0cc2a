//! `datagen validate`: every shard of a folder against its stats marker and the schema
//! ([`crate::corpus::validate`]).

use std::path::PathBuf;

use clap::Args;

/// Arguments of `datagen validate`.
#[derive(Debug, Args)]
pub struct ValidateArgs {
    /// A shard file or a folder of shards.
    pub path: PathBuf,
    /// Also decode every PNG and EXR and check its size.
    #[arg(long)]
    pub deep: bool,
}

/// Runs `datagen validate`: an error when any problem is found.
pub fn run(args: ValidateArgs) -> anyhow::Result<()> {
    let report = crate::corpus::validate::validate(&args.path, args.deep)?;
    for problem in &report.problems {
        println!("{}: {}", problem.path.display(), problem.message);
    }
    println!("{} shards, {} clips, {} problems", report.shards, report.clips, report.problems.len());
    if !report.problems.is_empty() {
        anyhow::bail!("validation found {} problems", report.problems.len());
    }
    Ok(())
}
