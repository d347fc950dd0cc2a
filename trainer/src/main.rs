//! The `trainer` command line: a thin layer over the library.

fn main() {
    println!("trainer {}: no subcommands yet", env!("CARGO_PKG_VERSION"));
}
