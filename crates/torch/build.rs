//! Compiles what promptdt needs of libtorch that tch 0.24 does not bind, against the headers of the
//! libtorch that torch-sys links: `LIBTORCH` (set by `.cargo/config.toml` to
//! `third_party/libtorch/torch`, installed by `scripts/fetch_libtorch.py`), with torch-sys's own
//! flags. `csrc/matmul.cpp`: cuBLAS's TF32 switch (`pdt_torch::device::set_matmul`);
//! `csrc/profiler.cpp`: libtorch's profiler (`pdt_torch::profiler`, `promptdt bench --profile`);
//! `csrc/memory.cpp`: pinned host memory without a deprecated argument (`pdt_torch::device::upload`);
//! `csrc/autocast.cpp`: libtorch's autocast switch (`pdt_torch::autocast`, `run.matmul = "bf16"`);
//! `csrc/bernoulli.cpp`: Bernoulli bits on the CPU, libtorch's drawn faster
//! (`pdt_torch::bernoulli`, for dropout's noise).

use std::path::PathBuf;

fn main() {
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed=csrc/matmul.cpp");
    println!("cargo::rerun-if-changed=csrc/profiler.cpp");
    println!("cargo::rerun-if-changed=csrc/memory.cpp");
    println!("cargo::rerun-if-changed=csrc/bernoulli.cpp");
    println!("cargo::rerun-if-changed=csrc/autocast.cpp");
    println!("cargo::rerun-if-changed=csrc/guard.h");
    println!("cargo::rerun-if-env-changed=LIBTORCH");
    println!("cargo::rerun-if-env-changed=LIBTORCH_CXX11_ABI");
    let Some(libtorch) = std::env::var_os("LIBTORCH").map(PathBuf::from) else {
        panic!(
            "LIBTORCH is not set: build from the workspace (its .cargo/config.toml sets it) after \
             `python3 scripts/fetch_libtorch.py`"
        );
    };
    let include = libtorch.join("include");
    if !include.join("ATen").join("Context.h").is_file() {
        panic!(
            "{} has no ATen/Context.h: install libtorch 2.11.0 with `python3 scripts/fetch_libtorch.py`",
            include.display()
        );
    }
    // torch-sys's default (the PyPI wheels are built with the C++11 ABI).
    let abi = std::env::var("LIBTORCH_CXX11_ABI").unwrap_or_else(|_| "1".into());
    cc::Build::new()
        .cpp(true)
        .file("csrc/matmul.cpp")
        .file("csrc/profiler.cpp")
        .file("csrc/memory.cpp")
        .file("csrc/bernoulli.cpp")
        .file("csrc/autocast.cpp")
        .include(&include)
        .include(include.join("torch").join("csrc").join("api").join("include"))
        .include(include.join("kineto"))
        .flag("-std=c++17")
        .flag(format!("-D_GLIBCXX_USE_CXX11_ABI={abi}"))
        .flag("-DGLOG_USE_GLOG_EXPORT")
        .warnings(false)
        .compile("pdt_libtorch_extra");
}
