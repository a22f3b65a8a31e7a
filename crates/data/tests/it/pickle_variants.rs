//! The small fixtures written by `scripts/golden/make_pickle_variants.py`: every protocol, numpy
//! 1.x and 2.x module names, the layout variants the reference loader accepts, and hostile files.
//! `variants.json` (written by the same script from numpy's own view of the data) says what each
//! must load to, or the error it must give.

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};

use pdt_data::inspect::inspect_file;
use pdt_data::pickle::{self, DType, NdArray, PickleError, PyValue};
use pdt_data::reference::{from_bytes, load_pickle, ReferenceOptions, TerminalsAs};
use serde_json::Value;

const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/pickle");

fn fixture(name: &str) -> PathBuf {
    Path::new(FIXTURES).join(name)
}

fn manifest() -> Vec<Value> {
    let text = fs::read_to_string(fixture("variants.json")).expect("variants.json");
    let v: Value = serde_json::from_str(&text).expect("variants.json is JSON");
    v.as_array().expect("a list").clone()
}

fn entries(kind: &str) -> Vec<Value> {
    manifest().into_iter().filter(|e| e["kind"] == kind).collect()
}

fn name_of(entry: &Value) -> &str {
    entry["file"].as_str().expect("file name")
}

fn f32s(v: &Value) -> Vec<f32> {
    v.as_array().expect("list").iter().map(|x| x.as_f64().expect("number") as f32).collect()
}

fn bools(v: &Value) -> Vec<bool> {
    v.as_array().expect("list").iter().map(|x| x.as_bool().expect("bool")).collect()
}

fn report(failures: Vec<String>) {
    assert!(failures.is_empty(), "{} failure(s):\n{}", failures.len(), failures.join("\n"));
}

#[test]
fn every_fixture_is_described_and_every_description_has_a_fixture() {
    let described: BTreeSet<String> = manifest().iter().map(|e| name_of(e).to_string()).collect();
    let on_disk: BTreeSet<String> = fs::read_dir(FIXTURES)
        .expect("fixture dir")
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.ends_with(".pkl"))
        .collect();
    assert_eq!(described, on_disk);
    // The categories the brief asks for are all there.
    for name in [
        "ref-p2.pkl",
        "ref-p3.pkl",
        "ref-p4.pkl",
        "ref-p5.pkl",
        "ref-p5-readonly.pkl",
        "ref-float64.pkl",
        "ref-dones.pkl",
        "ref-flat.pkl",
        "err-os-system.pkl",
        "err-truncated.pkl",
        "err-object-array.pkl",
    ] {
        assert!(described.contains(name), "{name} missing");
    }
}

#[test]
fn both_numpy_module_spellings_are_covered() {
    let has = |file: &str, needle: &[u8]| {
        let bytes = fs::read(fixture(file)).expect("fixture");
        bytes.windows(needle.len()).any(|w| w == needle)
    };
    // numpy 1.x, GLOBAL (protocols 2/3) and STACK_GLOBAL (4/5) forms.
    assert!(has("ref-p2-numpy1.pkl", b"cnumpy.core.multiarray\n_reconstruct\n"));
    assert!(has("ref-p3-numpy1.pkl", b"cnumpy.core.multiarray\n_reconstruct\n"));
    assert!(has("ref-p4-numpy1.pkl", b"\x8c\x15numpy.core.multiarray"));
    assert!(has("ref-p5-numpy1.pkl", b"\x8c\x12numpy.core.numeric"));
    assert!(has("ref-p5-numpy1.pkl", b"\x8c\x0b_frombuffer"));
    assert!(has("generic-p2-numpy1.pkl", b"cnumpy.core.multiarray\nscalar\n"));
    // numpy 2.x.
    assert!(has("ref-p2.pkl", b"cnumpy._core.multiarray\n_reconstruct\n"));
    assert!(has("ref-p4.pkl", b"\x8c\x16numpy._core.multiarray"));
    assert!(has("ref-p5.pkl", b"\x8c\x13numpy._core.numeric"));
    assert!(has("generic-p4.pkl", b"\x8c\x06scalar"));
    // Protocol 5 in-band buffers (writable: BYTEARRAY8) and protocol 2 bytes (_codecs.encode).
    assert!(has("ref-p5.pkl", b"\x96"));
    assert!(has("ref-p2.pkl", b"c_codecs\nencode\n"));
}

#[test]
fn reference_variants_load_to_the_values_numpy_wrote() {
    let mut failures = Vec::new();
    let all = entries("reference");
    assert!(all.len() >= 17, "only {} reference variants", all.len());
    for e in &all {
        let name = name_of(e);
        let horizon = e["horizon"].as_u64().expect("horizon") as usize;
        let opts = ReferenceOptions { terminals_as: TerminalsAs::Auto { horizon } };
        let loaded = match load_pickle(&fixture(name), &opts) {
            Ok(l) => l,
            Err(err) => {
                failures.push(format!("{name}: {err}"));
                continue;
            }
        };
        let ds = &loaded.dataset;
        let want_dims = (e["obs_dim"].as_u64(), e["act_dim"].as_u64());
        if want_dims != (Some(ds.obs_dim as u64), Some(ds.act_dim as u64)) {
            failures.push(format!("{name}: dims {} {}", ds.obs_dim, ds.act_dim));
        }
        let want = e["trajectories"].as_array().expect("trajectories");
        if want.len() != ds.trajectories.len() {
            failures.push(format!("{name}: {} trajectories", ds.trajectories.len()));
            continue;
        }
        for (i, (w, got)) in want.iter().zip(&ds.trajectories).enumerate() {
            let checks = [
                ("observations", f32s(&w["observations"]) == got.observations),
                ("actions", f32s(&w["actions"]) == got.actions),
                ("rewards", f32s(&w["rewards"]) == got.rewards),
                ("terminated", bools(&w["terminated"]) == got.terminated),
                ("truncated", bools(&w["truncated"]) == got.truncated),
            ];
            for (field, ok) in checks {
                if !ok {
                    failures.push(format!("{name}: trajectory {i}: `{field}` differs"));
                }
            }
        }
        let arrays: Vec<(String, String, Vec<usize>)> = loaded
            .arrays
            .iter()
            .map(|a| (a.key.clone(), a.dtype.clone(), a.shape.clone()))
            .collect();
        let want_arrays: Vec<(String, String, Vec<usize>)> = e["arrays"]
            .as_array()
            .expect("arrays")
            .iter()
            .map(|a| {
                let shape = a["shape"].as_array().expect("shape");
                (
                    a["key"].as_str().expect("key").to_string(),
                    a["dtype"].as_str().expect("dtype").to_string(),
                    shape.iter().map(|d| d.as_u64().expect("dim") as usize).collect(),
                )
            })
            .collect();
        if arrays != want_arrays {
            failures.push(format!("{name}: arrays {arrays:?}, expected {want_arrays:?}"));
        }
    }
    report(failures);
}

#[test]
fn from_bytes_agrees_with_load_pickle() {
    let opts = ReferenceOptions::default();
    let path = fixture("ref-p4.pkl");
    let a = load_pickle(&path, &opts).expect("load");
    let b = from_bytes(&fs::read(&path).expect("read"), &opts).expect("from_bytes");
    assert_eq!(a, b);
}

#[test]
fn terminal_modes_on_the_terminals_fixture() {
    // Lengths 5, 3, 4; flags at the end of the first two only.
    let load = |how| {
        let opts = ReferenceOptions { terminals_as: how };
        let ds = load_pickle(&fixture("ref-terminals.pkl"), &opts).expect("load").dataset;
        ds.trajectories
            .iter()
            .map(|t| (t.terminated.clone(), t.truncated.clone()))
            .collect::<Vec<_>>()
    };
    let ends = |v: &[(Vec<bool>, Vec<bool>)]| -> Vec<(bool, bool)> {
        v.iter()
            .map(|(te, tr)| {
                // Nothing is flagged anywhere but the last step.
                let n = te.len();
                assert!(te[..n - 1].iter().chain(&tr[..n - 1]).all(|&f| !f));
                (te[n - 1], tr[n - 1])
            })
            .collect()
    };
    // (terminated, truncated) at the last step of each trajectory.
    assert_eq!(
        ends(&load(TerminalsAs::Auto { horizon: 5 })),
        vec![(false, true), (true, false), (false, true)]
    );
    assert_eq!(
        ends(&load(TerminalsAs::Auto { horizon: 200 })),
        vec![(true, false), (true, false), (false, true)]
    );
    assert_eq!(
        ends(&load(TerminalsAs::Terminated)),
        vec![(true, false), (true, false), (false, true)]
    );
    assert_eq!(
        ends(&load(TerminalsAs::Truncated)),
        vec![(false, true), (false, true), (false, true)]
    );
}

#[test]
fn inspect_reports_a_fixture() {
    let r = inspect_file(&fixture("ref-terminals.pkl")).expect("inspect");
    assert_eq!(r.format, "reference-pickle");
    assert_eq!((r.trajectories, r.steps, r.obs_dim, r.act_dim), (3, 12, 3, 2));
    assert_eq!((r.length_min, r.length_max), (3, 5));
    assert!(r.return_min <= r.return_mean && r.return_mean <= r.return_max);
    let keys: Vec<&str> = r.dtypes.iter().map(|a| a.key.as_str()).collect();
    assert_eq!(keys, ["observations", "next_observations", "actions", "rewards", "terminals"]);
    assert_eq!(r.dtypes[4].dtype, "bool");
    assert_eq!(r.dtypes[4].shape, [5, 1]);
}

// ------------------------------------------------------------------------------------------------
// Generic value trees
// ------------------------------------------------------------------------------------------------

fn dtype_named(name: &str) -> DType {
    let all = [
        DType::Bool,
        DType::Int8,
        DType::Int16,
        DType::Int32,
        DType::Int64,
        DType::UInt8,
        DType::UInt16,
        DType::UInt32,
        DType::UInt64,
        DType::Float32,
        DType::Float64,
    ];
    *all.iter().find(|d| d.name() == name).unwrap_or_else(|| panic!("dtype {name}"))
}

fn hex(s: &str) -> Vec<u8> {
    (0..s.len() / 2).map(|i| u8::from_str_radix(&s[2 * i..2 * i + 2], 16).expect("hex")).collect()
}

/// The tagged JSON tree -> the value the parser must return (arrays with C-order data).
fn expected(v: &Value) -> PyValue {
    let t = v.as_array().expect("tagged value");
    let items =
        |x: &Value| -> Vec<PyValue> { x.as_array().expect("list").iter().map(expected).collect() };
    match t[0].as_str().expect("tag") {
        "none" => PyValue::None,
        "bool" => PyValue::Bool(t[1].as_bool().expect("bool")),
        "int" => PyValue::Int(t[1].as_i64().expect("int")),
        "float" => PyValue::Float(t[1].as_f64().expect("float")),
        "str" => PyValue::Str(t[1].as_str().expect("str").to_string()),
        "bytes" => PyValue::Bytes(hex(t[1].as_str().expect("hex"))),
        "list" => PyValue::List(items(&t[1])),
        "tuple" => PyValue::Tuple(items(&t[1])),
        "dict" => PyValue::Dict(
            t[1].as_array()
                .expect("pairs")
                .iter()
                .map(|p| (expected(&p[0]), expected(&p[1])))
                .collect(),
        ),
        "nd" => PyValue::NdArray(NdArray {
            dtype: dtype_named(t[1].as_str().expect("dtype")),
            shape: t[2]
                .as_array()
                .expect("shape")
                .iter()
                .map(|d| d.as_u64().expect("dim") as usize)
                .collect(),
            fortran_order: t[3].as_bool().expect("fortran"),
            data: hex(t[4].as_str().expect("hex")),
        }),
        other => panic!("unknown tag {other}"),
    }
}

/// Compares trees; arrays by dtype, shape, layout flag and C-order data; floats to 1 ulp-ish
/// (JSON float parsing need not be correctly rounded).
fn compare(got: &PyValue, want: &PyValue, at: &str, out: &mut Vec<String>) {
    match (got, want) {
        (PyValue::Float(a), PyValue::Float(b)) => {
            if (a - b).abs() > 1e-15 * b.abs() {
                out.push(format!("{at}: {a} != {b}"));
            }
        }
        (PyValue::List(a), PyValue::List(b)) | (PyValue::Tuple(a), PyValue::Tuple(b)) => {
            if a.len() != b.len() {
                out.push(format!("{at}: length {} != {}", a.len(), b.len()));
                return;
            }
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                compare(x, y, &format!("{at}[{i}]"), out);
            }
        }
        (PyValue::Dict(a), PyValue::Dict(b)) => {
            if a.len() != b.len() {
                out.push(format!("{at}: {} keys != {}", a.len(), b.len()));
                return;
            }
            for ((ka, va), (kb, vb)) in a.iter().zip(b) {
                compare(ka, kb, &format!("{at} key"), out);
                compare(va, vb, &format!("{at}[{ka:?}]"), out);
            }
        }
        (PyValue::NdArray(a), PyValue::NdArray(b)) => {
            let c = a.to_c_order();
            if (a.dtype, &a.shape, a.fortran_order, &c.data)
                != (b.dtype, &b.shape, b.fortran_order, &b.data)
            {
                out.push(format!("{at}: array {a:?} (C order {:?}) != {b:?}", c.data));
            }
        }
        _ => {
            if got != want {
                out.push(format!("{at}: {got:?} != {want:?}"));
            }
        }
    }
}

#[test]
fn generic_variants_parse_to_the_values_python_wrote() {
    let all = entries("generic");
    assert!(all.len() >= 6);
    let mut failures = Vec::new();
    for e in &all {
        let name = name_of(e);
        let bytes = fs::read(fixture(name)).expect("fixture");
        match pickle::parse(&bytes) {
            Ok(got) => compare(&got, &expected(&e["value"]), name, &mut failures),
            Err(err) => failures.push(format!("{name}: {err}")),
        }
    }
    report(failures);
}

#[test]
fn generic_tree_has_what_the_script_put_in() {
    // A direct look at a few values, independent of the JSON decoding above.
    let v = pickle::parse(&fs::read(fixture("generic-p4.pkl")).expect("fixture")).expect("parse");
    assert_eq!(v.get("str"), Some(&PyValue::Str("héllo ✓".into())));
    assert_eq!(v.get("empty_bytes"), Some(&PyValue::Bytes(vec![])));
    let Some(PyValue::NdArray(big)) = v.get("big_f8") else { panic!("big_f8") };
    assert_eq!(big.to_f64_vec(), vec![1.5, -2.0, 1e-10]);
    let Some(PyValue::NdArray(f)) = v.get("fortran") else { panic!("fortran") };
    assert!(f.fortran_order);
    let c: Vec<f64> = f.to_f64_vec();
    assert_eq!(c, (0..24).map(f64::from).collect::<Vec<_>>());
    let Some(PyValue::NdArray(s)) = v.get("scalar_f32") else { panic!("scalar") };
    assert_eq!((s.shape.len(), s.to_f32_vec()), (0, Some(vec![1.5])));
    let Some(PyValue::List(ints)) = v.get("ints") else { panic!("ints") };
    assert_eq!(ints.last(), Some(&PyValue::Int(i64::MAX)));
}

// ------------------------------------------------------------------------------------------------
// Files that must be refused
// ------------------------------------------------------------------------------------------------

#[test]
fn error_variants_fail_with_the_expected_message() {
    let all = entries("error");
    assert!(all.len() >= 13);
    let mut failures = Vec::new();
    for e in &all {
        let name = name_of(e);
        let path = fixture(name);
        let bytes = fs::read(&path).expect("fixture");
        let layer = e["layer"].as_str().expect("layer");
        let parsed = pickle::parse(&bytes);
        match (layer, &parsed) {
            ("pickle", Ok(_)) => failures.push(format!("{name}: parsed, expected a pickle error")),
            ("reference", Err(err)) => failures.push(format!("{name}: pickle error {err}")),
            _ => {}
        }
        // Whatever the layer, the loader's message names the file and says what is wrong.
        let message = match load_pickle(&path, &ReferenceOptions::default()) {
            Ok(_) => {
                failures.push(format!("{name}: loaded, expected an error"));
                continue;
            }
            Err(err) => err.to_string(),
        };
        if !message.contains(name) {
            failures.push(format!("{name}: message does not name the file: {message}"));
        }
        for want in e["error_contains"].as_array().expect("error_contains") {
            let want = want.as_str().expect("str");
            if !message.contains(want) {
                failures.push(format!("{name}: message lacks {want:?}: {message}"));
            }
        }
    }
    report(failures);
}

#[test]
fn forbidden_globals_are_refused_where_they_are_named() {
    // The error is at the GLOBAL opcode (byte 2), before the REDUCE that would call it.
    let bytes = fs::read(fixture("err-os-system.pkl")).expect("fixture");
    match pickle::parse(&bytes) {
        Err(PickleError::GlobalNotAllowed { offset, opcode, module, name }) => {
            assert_eq!(
                (offset, opcode, module.as_str(), name.as_str()),
                (2, "GLOBAL", "os", "system")
            );
        }
        other => panic!("expected GlobalNotAllowed, got {other:?}"),
    }
    let bytes = fs::read(fixture("err-builtins-eval.pkl")).expect("fixture");
    assert!(matches!(
        pickle::parse(&bytes),
        Err(PickleError::GlobalNotAllowed { opcode: "STACK_GLOBAL", ref module, ref name, .. })
            if module == "builtins" && name == "eval"
    ));
    // Other dangerous names, in both spellings of the opcode.
    for (module, name) in
        [("builtins", "exec"), ("subprocess", "Popen"), ("numpy", "load"), ("posix", "system")]
    {
        let mut g = b"\x80\x02c".to_vec();
        g.extend_from_slice(format!("{module}\n{name}\n").as_bytes());
        g.extend_from_slice(b")R.");
        let e = pickle::parse(&g).expect_err("must refuse");
        assert!(e.to_string().contains(&format!("global {module}.{name} is not allowed")), "{e}");
    }
}
