//! The `datagen` command line: parses the arguments and runs the command ([`datagen::cli`], one
//! file per command), mapping the result to the exit code: 0 on success, 1 when the command
//! fails, 2 for invalid arguments.

use std::process::ExitCode;

use clap::Parser;
use datagen::cli::Cli;

// Every frame allocates and drops tens of MB of meshes and bins; glibc returns such blocks to
// the kernel and faults them back in each time (a visible share of `pairs`' CPU), mimalloc reuses
// them. Its `no_thp` feature keeps it from asking for transparent huge pages: each fresh 2 MB page
// is cleared whole when first touched, also where only part of it is used (the encoders' growing
// output buffers). `scripts/bench_pairs_vs.sh` measures the peak RSS and wall time it saves.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(error) if error.use_stderr() => {
            // One line naming the parameter; `--help` has the rest.
            let message = error.to_string();
            eprintln!("{}", message.lines().next().unwrap_or("error: invalid arguments"));
            return ExitCode::from(2);
        }
        Err(error) => {
            let _ = error.print();
            return ExitCode::SUCCESS;
        }
    };
    match cli.command.run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}
