//! The rpath and CUDA link arguments of `build_link.rs`, then the c10d shim (`csrc/`), compiled
//! with `cc` against the same libtorch's headers (as tch's torch-sys builds its own wrapper):
//! TCPStore and ProcessGroupGloo always (gloo's headers come from Debian's libgloo-dev),
//! ProcessGroupNCCL when libtorch_cuda.so is there and the nvidia wheels' `nccl.h` sits beside the
//! torch package (`site-packages/nvidia/*/include`). `TRAINER_NO_NCCL=1` leaves the NCCL half out.

mod build_link;

use std::path::{Path, PathBuf};

/// Emits the link arguments and builds the c10d shim.
pub fn main() {
    println!("cargo:rerun-if-env-changed=TRAINER_NO_NCCL");
    for file in ["csrc/c10d_shim.cpp", "csrc/c10d_nccl.cpp", "csrc/c10d_shim.h", "build_link.rs"] {
        println!("cargo:rerun-if-changed={file}");
    }
    let (libtorch, cuda) = build_link::emit();
    build_c10d_shim(&libtorch, cuda);
}

/// Compiles `csrc/` into a static library linked into the `trainer` crate.
fn build_c10d_shim(libtorch: &Path, cuda: bool) {
    let include = libtorch.join("include");
    let abi = std::env::var("LIBTORCH_CXX11_ABI").unwrap_or_else(|_| "1".to_string());
    let mut build = cc::Build::new();
    build
        .cpp(true)
        .std("c++17")
        .files(["csrc/c10d_shim.cpp", "csrc/c10d_nccl.cpp"])
        .include(&include)
        .include(include.join("torch/csrc/api/include"))
        // Without it ProcessGroupGloo.hpp declares nothing.
        .define("USE_C10D_GLOO", None)
        .define("_GLIBCXX_USE_CXX11_ABI", abi.as_str())
        // torch's own headers warn under -Wall; the shim's few lines are read by eye.
        .warnings(false);
    let no_nccl = std::env::var("TRAINER_NO_NCCL").is_ok_and(|v| v == "1");
    if cuda && !no_nccl {
        let nvidia = libtorch.parent().map(|site| site.join("nvidia"));
        let includes: Vec<PathBuf> = nvidia
            .and_then(|dir| std::fs::read_dir(dir).ok())
            .into_iter()
            .flatten()
            .filter_map(|entry| Some(entry.ok()?.path().join("include")))
            .filter(|dir| dir.is_dir())
            .collect();
        if includes.iter().any(|dir| dir.join("nccl.h").exists()) {
            build
                .includes(&includes)
                .define("USE_C10D_NCCL", None)
                .define("USE_CUDA", None)
                .define("TRAINER_C10D_NCCL", None);
        } else {
            println!(
                "cargo:warning=libtorch_cuda.so found but no nccl.h under {}/../nvidia/*/include: building without NCCL",
                libtorch.display()
            );
        }
    }
    build.compile("trainer_c10d");
    // The shim's references into libtorch resolve against the libraries tch links; naming them
    // after the static library keeps the link order right.
    println!("cargo:rustc-link-search=native={}", libtorch.join("lib").display());
    println!("cargo:rustc-link-lib=dylib=torch_cpu");
    println!("cargo:rustc-link-lib=dylib=c10");
    if cuda {
        println!("cargo:rustc-link-lib=dylib=torch_cuda");
        // The CUDA caching allocator's statistics (the shim's memory peaks).
        println!("cargo:rustc-link-lib=dylib=c10_cuda");
    }
}
