//! The pickle reader on broken and hostile input: it must return an error, never panic, and never
//! allocate more than the input justifies.
//!
//! Allocation is measured, not assumed: this test binary installs a counting global allocator
//! that records, per thread, the peak of live heap bytes and the largest single request while
//! `parse` runs, and refuses (returns null for) any request beyond the allowance, so a parser
//! that tries to build gigabytes aborts the test at once ("memory allocation of N bytes failed")
//! instead of being killed by the OOM killer, or passing on a machine with enough memory.
//!
//! `tests/fixtures/pickle/corpus/` keeps the interesting inputs (seeds, hand-made edge cases,
//! and anything the property tests ever found): `ok-*` must parse, `err-*` must fail.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::fs;
use std::path::{Path, PathBuf};

use pdt_data::pickle::{parse, PickleError, PyValue};
use proptest::prelude::*;
use proptest::test_runner::FileFailurePersistence;

// ------------------------------------------------------------------------------------------------
// Counting allocator
// ------------------------------------------------------------------------------------------------

struct Counting;

thread_local! {
    // const-initialised Cells without destructors: using them never allocates, so the allocator
    // cannot recurse into itself.
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
    static LARGEST: Cell<usize> = const { Cell::new(0) };
    /// Live bytes this thread may hold; 0 means no limit (outside `parse_bounded`).
    static LIMIT: Cell<usize> = const { Cell::new(0) };
}

/// Records an allocation; false if it would exceed the thread's limit (it is then refused).
fn on_alloc(size: usize) -> bool {
    let limit = LIMIT.try_with(Cell::get).unwrap_or(0);
    let live = LIVE.try_with(Cell::get).unwrap_or(0);
    let now = live.saturating_add(size);
    if limit != 0 && now > limit {
        return false;
    }
    let _ = LIVE.try_with(|c| c.set(now));
    let _ = PEAK.try_with(|p| p.set(p.get().max(now)));
    let _ = LARGEST.try_with(|l| l.set(l.get().max(size)));
    true
}

fn on_free(size: usize) {
    let _ = LIVE.try_with(|live| live.set(live.get().saturating_sub(size)));
}

// SAFETY: every method forwards to the system allocator with the caller's arguments unchanged;
// the only addition is bookkeeping in thread-local Cells, which neither allocates nor touches the
// memory being managed.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !on_alloc(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: same contract as our caller's.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !on_alloc(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: same contract as our caller's.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        on_free(layout.size());
        // SAFETY: same contract as our caller's.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        on_free(layout.size());
        if !on_alloc(new_size) {
            // The old block stays valid and is still counted, as realloc's contract says.
            on_alloc(layout.size());
            return std::ptr::null_mut();
        }
        // SAFETY: same contract as our caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// What the input may cost: the parser's value budget is 64 bytes per input byte + 1 MiB; its
/// working structures (object arena, stack, memo, each at most one entry per opcode, with `Vec`
/// doubling) add a few hundred bytes per opcode at worst.
fn allowance(input_len: usize) -> usize {
    512 * input_len + (4 << 20)
}

/// `parse`, failing the test if it allocated more than [`allowance`] at any moment (a request
/// over the allowance aborts the test binary).
fn parse_bounded(bytes: &[u8]) -> Result<PyValue, PickleError> {
    let limit = allowance(bytes.len());
    LIVE.with(|c| c.set(0));
    PEAK.with(|c| c.set(0));
    LARGEST.with(|c| c.set(0));
    LIMIT.with(|c| c.set(limit));
    let result = parse(bytes);
    LIMIT.with(|c| c.set(0));
    let peak = PEAK.with(Cell::get);
    let largest = LARGEST.with(Cell::get);
    assert!(
        peak <= limit && largest <= limit,
        "{}-byte input: peak {peak} bytes, largest allocation {largest}, allowed {limit}",
        bytes.len()
    );
    result
}

// ------------------------------------------------------------------------------------------------
// Inputs
// ------------------------------------------------------------------------------------------------

const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/pickle");

fn files_in(dir: &Path, pred: impl Fn(&str) -> bool) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .filter_map(|e| Some(e.ok()?.path()))
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(&pred))
        .collect();
    files.sort();
    files
}

/// The valid fixtures (every protocol, every value kind).
fn valid_fixtures() -> Vec<(String, Vec<u8>)> {
    let files = files_in(Path::new(FIXTURES), |n| {
        (n.starts_with("ref-") || n.starts_with("generic-")) && n.ends_with(".pkl")
    });
    assert!(files.len() >= 20, "fixtures missing: run scripts/golden/make_pickle_variants.py");
    files
        .into_iter()
        .map(|p| {
            let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            (name, fs::read(&p).expect("read fixture"))
        })
        .collect()
}

// ------------------------------------------------------------------------------------------------
// Deterministic checks
// ------------------------------------------------------------------------------------------------

#[test]
fn every_prefix_of_every_small_fixture_is_an_error() {
    for (name, bytes) in valid_fixtures() {
        assert!(parse_bounded(&bytes).is_ok(), "{name} itself must parse");
        for cut in 0..bytes.len() {
            if let Ok(v) = parse_bounded(&bytes[..cut]) {
                panic!("{name}: prefix of {cut} bytes parsed as {v:?}");
            }
        }
    }
}

#[test]
fn prefixes_of_an_official_file_are_errors() {
    // The reference release's data (pdt_testkit::reference): skipped without it, except in CI.
    let official = pdt_testkit::reference::official_prompt("cheetah_vel-2-prompt-expert.pkl");
    let Some(official) = official else { return };
    let bytes = fs::read(&official).expect("official file");
    assert!(parse_bounded(&bytes).is_ok());
    // A stride through the whole file, plus every cut near the start and the end, where the
    // structure (frames, list, first dict, final SETITEMS/APPENDS/STOP) is.
    let near_ends = (0..300).chain(bytes.len() - 300..bytes.len());
    for cut in (0..bytes.len()).step_by(997).chain(near_ends) {
        match parse_bounded(&bytes[..cut]) {
            Ok(_) => panic!("prefix of {cut} bytes parsed"),
            Err(PickleError::Truncated { .. } | PickleError::NoStop { .. }) => {}
            // A cut can also leave a well-formed but incomplete program, e.g. a short string
            // where STACK_GLOBAL expects its name.
            Err(e) => assert!(cut < 300 || bytes.len() - cut < 300, "cut {cut}: {e}"),
        }
    }
}

#[test]
fn huge_length_claims_fail_before_allocating() {
    let cases: [(&[u8], &str); 7] = [
        (b"\x80\x04\x8e\x00\x00\x00\x00\x00\x00\x00\x10abc.", "BINBYTES8"),
        (b"\x80\x04\x8e\xff\xff\xff\xff\xff\xff\xff\xff.", "BINBYTES8"),
        (b"\x80\x04\x8d\xff\xff\xff\xff\xff\xff\xff\x7f.", "BINUNICODE8"),
        (b"\x80\x05\x96\x00\x00\x00\x00\x00\x00\x00\x01.", "BYTEARRAY8"),
        (b"\x80\x03B\xff\xff\xff\xff.", "BINBYTES"),
        (b"\x80\x02X\xff\xff\xff\x7f.", "BINUNICODE"),
        (b"\x80\x02\x8b\xff\xff\xff\x7f.", "LONG4"),
    ];
    for (bytes, op) in cases {
        LARGEST.with(|c| c.set(0));
        match parse_bounded(bytes) {
            Err(PickleError::Truncated { opcode, offset: 2, .. }) => assert_eq!(opcode, op),
            other => panic!("{op}: {other:?}"),
        }
        assert!(LARGEST.with(Cell::get) < 4096, "{op} allocated {}", LARGEST.with(Cell::get));
    }
}

#[test]
fn corpus_replays() {
    let dir = Path::new(FIXTURES).join("corpus");
    let files = files_in(&dir, |n| n.starts_with("ok-") || n.starts_with("err-"));
    assert!(files.len() >= 40, "corpus has {} files", files.len());
    for path in files {
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let bytes = fs::read(&path).expect("read corpus file");
        let result = parse_bounded(&bytes);
        match (name.starts_with("ok-"), &result) {
            (true, Err(e)) => panic!("{name}: {e}"),
            (false, Ok(v)) => panic!("{name}: parsed as {v:?}"),
            _ => {}
        }
        // The attacks that only a resource limit stops must be stopped by one.
        if ["err-billion-laughs", "err-frombuffer-amplify", "err-deep-nesting", "err-cycle"]
            .iter()
            .any(|p| name.starts_with(p))
        {
            assert!(matches!(result, Err(PickleError::Limit { .. })), "{name}: {result:?}");
        }
    }
}

#[test]
fn corpus_edge_cases_mean_what_they_say() {
    let read = |n: &str| fs::read(Path::new(FIXTURES).join("corpus").join(n)).expect("corpus file");
    assert_eq!(
        parse_bounded(&read("ok-long-binput-max.bin")).ok(),
        Some(PyValue::Tuple(vec![PyValue::None, PyValue::None]))
    );
    assert_eq!(parse_bounded(&read("ok-long4.bin")).ok(), Some(PyValue::Int(-32767)));
    assert_eq!(parse_bounded(&read("ok-trailing-bytes.bin")).ok(), Some(PyValue::Int(7)));
    assert_eq!(
        parse_bounded(&read("ok-binbytes8.bin")).ok(),
        Some(PyValue::Bytes(b"abc".to_vec()))
    );
    assert_eq!(
        parse_bounded(&read("ok-duplicate-key.bin")).ok(),
        Some(PyValue::Dict(vec![(PyValue::Int(1), PyValue::Int(3))]))
    );
    let e = parse_bounded(&read("err-shape-overflow.bin")).expect_err("overflow");
    assert!(e.to_string().contains("overflows"), "{e}");
    let e = parse_bounded(&read("err-shape-mismatch.bin")).expect_err("mismatch");
    assert!(e.to_string().contains("needs"), "{e}");
    let e = parse_bounded(&read("err-inst.bin")).expect_err("INST");
    assert!(matches!(e, PickleError::UnsupportedOpcode { opcode: "INST", .. }), "{e}");
}

// ------------------------------------------------------------------------------------------------
// Property tests
// ------------------------------------------------------------------------------------------------

#[derive(Debug, Clone)]
enum Edit {
    Set(usize, u8),
    Insert(usize, Vec<u8>),
    Delete(usize, usize),
    /// Overwrite 8 bytes with a large little-endian number: the typical hostile length field.
    BigNumber(usize, u64),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), any::<u8>()).prop_map(|(p, b)| Edit::Set(p, b)),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(p, v)| Edit::Insert(p, v)),
        (any::<usize>(), 1usize..32).prop_map(|(p, n)| Edit::Delete(p, n)),
        (any::<usize>(), prop_oneof![Just(u64::MAX), Just(1 << 60), Just(1 << 32), 0u64..1 << 20])
            .prop_map(|(p, n)| Edit::BigNumber(p, n)),
    ]
}

fn apply(mut bytes: Vec<u8>, edits: &[Edit]) -> Vec<u8> {
    for e in edits {
        let len = bytes.len().max(1);
        match e {
            Edit::Set(p, b) => {
                if let Some(slot) = bytes.get_mut(p % len) {
                    *slot = *b;
                }
            }
            Edit::Insert(p, v) => {
                let at = p % (bytes.len() + 1);
                bytes.splice(at..at, v.iter().copied());
            }
            Edit::Delete(p, n) => {
                let at = p % len;
                let end = (at + n).min(bytes.len());
                if at < end {
                    bytes.drain(at..end);
                }
            }
            Edit::BigNumber(p, n) => {
                let at = p % len;
                for (slot, b) in bytes.iter_mut().skip(at).zip(n.to_le_bytes()) {
                    *slot = b;
                }
            }
        }
    }
    bytes
}

/// Opcodes with plausible arguments, so that random programs get past the first few bytes.
fn token() -> impl Strategy<Value = Vec<u8>> {
    let op = |code: u8, args: Vec<u8>| {
        let mut v = vec![code];
        v.extend(args);
        v
    };
    prop_oneof![
        prop::sample::select(b"(.012NR]})ealtdsuhb\x85\x86\x87\x88\x89\x93\x94".to_vec())
            .prop_map(|c| vec![c]),
        (prop::sample::select(vec![b'K', b'h', b'q', b'C', 0x8a]), any::<u8>())
            .prop_map(move |(c, a)| op(c, vec![a])),
        (prop::sample::select(vec![b'J', b'j', b'r', b'X', b'B', 0x8b]), any::<[u8; 4]>())
            .prop_map(move |(c, a)| op(c, a.to_vec())),
        (prop::sample::select(vec![0x8c_u8, b'C']), "[a-z_.]{0,24}").prop_map(|(c, s)| {
            let mut v = vec![c, s.len() as u8];
            v.extend(s.bytes());
            v
        }),
        prop::sample::select(vec![
            b"cnumpy\ndtype\n".to_vec(),
            b"cnumpy\nndarray\n".to_vec(),
            b"cnumpy._core.multiarray\n_reconstruct\n".to_vec(),
            b"cnumpy._core.multiarray\nscalar\n".to_vec(),
            b"cnumpy._core.numeric\n_frombuffer\n".to_vec(),
            b"c_codecs\nencode\n".to_vec(),
            b"\x8c\x02f4".to_vec(),
            b"\x8c\x02b1".to_vec(),
            b"\x8c\x01<".to_vec(),
            b"\x8c\x01C".to_vec(),
            b"\x8c\x06latin1".to_vec(),
        ]),
        (
            prop::sample::select(vec![0x8d_u8, 0x8e, 0x96, 0x95]),
            any::<u64>(),
            prop::collection::vec(any::<u8>(), 0..12)
        )
            .prop_map(|(c, n, tail)| {
                let mut v = vec![c];
                v.extend((n % 64).to_le_bytes());
                v.extend(tail);
                v
            }),
    ]
}

fn seeds() -> Vec<Vec<u8>> {
    valid_fixtures().into_iter().map(|(_, b)| b).collect()
}

fn config() -> ProptestConfig {
    ProptestConfig {
        // PROPTEST_CASES=100000 for a longer hunt; 1500 keeps the suite fast.
        cases: std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(1500),
        failure_persistence: Some(Box::new(FileFailurePersistence::Direct(
            "proptest-regressions/pickle_robustness.txt",
        ))),
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn mutated_fixtures_never_panic_or_overallocate(
        seed in any::<prop::sample::Index>(),
        edits in prop::collection::vec(edit(), 1..8),
    ) {
        let seeds = seeds();
        let bytes = apply(seed.get(&seeds).clone(), &edits);
        let _ = parse_bounded(&bytes);
    }

    #[test]
    fn random_programs_never_panic_or_overallocate(
        tokens in prop::collection::vec(token(), 0..80),
        proto in 2u8..=5,
    ) {
        let mut bytes = vec![0x80, proto];
        for t in tokens {
            bytes.extend(t);
        }
        bytes.push(b'.');
        let _ = parse_bounded(&bytes);
    }

    #[test]
    fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        let _ = parse_bounded(&bytes);
    }
}
