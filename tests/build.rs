//! The end-to-end test binaries link libtorch through `trainer`: same rpath rule as there.

#[path = "../trainer/build_link.rs"]
mod libtorch_link;

fn main() {
    libtorch_link::emit();
}
