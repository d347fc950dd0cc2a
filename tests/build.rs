//! The end-to-end test binaries link libtorch through `trainer`: same rpath rule as there.

#[path = "../trainer/build.rs"]
mod libtorch_rpath;

fn main() {
    libtorch_rpath::main();
}
