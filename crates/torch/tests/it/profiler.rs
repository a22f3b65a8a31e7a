//! libtorch's profiler through `pdt_torch::profiler` (csrc/profiler.cpp): it sees exactly the
//! operators run between start and stop, and a second profiler at once is refused, not a crash. The
//! profiler is process-wide: the test holds the test binary's libtorch lock (`pdt_testkit::process`),
//! so no other test runs an operator meanwhile.
#![allow(clippy::unwrap_used)] // test: a failed unwrap is a failed test

use pdt_torch::profiler::{start, EventKind};
use tch::{Device, Kind, Tensor};

#[test]
fn the_profiler_counts_the_operators_between_start_and_stop() {
    let _g = pdt_testkit::process::libtorch();
    let a = Tensor::randn([64, 32], (Kind::Float, Device::Cpu));
    let b = Tensor::randn([32, 16], (Kind::Float, Device::Cpu));
    let _ = a.mm(&b); // before: not recorded
    let p = start(false).unwrap();
    let e = start(false).unwrap_err().to_string();
    assert!(e.starts_with("libtorch's profiler: "), "{e}");
    for _ in 0..3 {
        let _ = a.mm(&b);
    }
    let _ = a.relu();
    let events = p.stop().unwrap();
    let _ = a.mm(&b); // after: not recorded
    let count = |name: &str| events.iter().filter(|e| e.name == name).count();
    assert_eq!(count("aten::mm"), 3, "{events:?}");
    assert_eq!(count("aten::relu"), 1, "{events:?}");
    assert!(events.iter().all(|e| e.kind == EventKind::Op), "{events:?}");
    assert!(events.iter().any(|e| e.duration_ns > 0), "{events:?}");
    // A profiler dropped without stop stops: the next one starts.
    drop(start(false).unwrap());
    let events = start(false).unwrap().stop().unwrap();
    assert!(events.iter().all(|e| e.name != "aten::mm"), "{events:?}");
}
