//! The `trainer` command line: parses the arguments, runs the command through the library
//! ([`trainer::cli`], where every command's flags and its conversion into a request live) and
//! maps how it ended to the exit status.

use trainer::cli::{self, Ended};
use trainer::training::preempt;

fn main() -> anyhow::Result<()> {
    let cli = cli::parse_from(std::env::args_os()).unwrap_or_else(|e| e.exit());
    let training = cli.command.is_training_run();
    exit(cli::run(cli.command), training)
}

/// Ends the process with the command's documented exit status (README, "Long runs"): 0 done,
/// 75 preempted after a complete checkpoint, 74 a training run's checkpoint could not be
/// written, 1 any other error (printed by `main`'s `Result`).
fn exit(result: anyhow::Result<Ended>, training: bool) -> anyhow::Result<()> {
    match result {
        Ok(Ended::Done) => Ok(()),
        Ok(Ended::Preempted) => std::process::exit(preempt::EXIT_PREEMPTED),
        Err(e) if training && matches!(e.downcast_ref(), Some(trainer::Error::CheckpointWrite { .. })) => {
            eprintln!("Error: {e:?}");
            std::process::exit(preempt::EXIT_CHECKPOINT_FAILED)
        }
        Err(e) => Err(e),
    }
}
