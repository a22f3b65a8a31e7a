//! The worker's framing, both ways: a frame is one line of JSON (the header), then, when the
//! header has `"payload": n`, `n` little-endian f32 values as raw bytes (`4 n` bytes). Actions,
//! observations and rewards travel in the payload: no float is printed and parsed, and a vector
//! step of many environments costs one short line of JSON plus its numbers. The requests and
//! replies are documented in `docs/your-own-tasks.md` and implemented on the Python side by
//! `promptdt/worker.py`.

use std::io::{BufRead, Read, Write};

use serde::Deserialize;

/// The protocol's version, sent with the first request; the worker refuses another.
pub(super) const VERSION: u32 = 1;

/// A longest header line: beyond it the stream is not the worker's (a stray print would be caught
/// earlier, since the worker sends its own prints to stderr; this bounds a garbled stream).
const MAX_HEADER: usize = 1 << 24;

/// A reply's header; which fields are there depends on the request.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct Reply {
    /// `init`'s answer: every environment was made.
    #[serde(default)]
    pub ok: bool,
    /// Why the request failed as a whole (e.g. an environment's factory raised: the last line of
    /// its traceback).
    #[serde(default)]
    pub error: Option<String>,
    /// The environment (its place in the batch) the `error` is about, where it is about one.
    #[serde(default)]
    pub slot: Option<usize>,
    /// The environments answered, in order: one payload row each.
    #[serde(default)]
    pub slots: Vec<usize>,
    #[serde(default)]
    pub terminated: Vec<bool>,
    #[serde(default)]
    pub truncated: Vec<bool>,
    /// `info.get("success")` per environment answered (`null` where absent).
    #[serde(default)]
    pub success: Vec<Option<bool>>,
    /// `[slot, message]` for each environment whose `step` raised (its payload row is zeros).
    #[serde(default)]
    pub errors: Vec<(usize, String)>,
    /// A collection's request (`act`): the environments whose policy acted on their new
    /// observation, in order; their actions end the payload.
    #[serde(default)]
    pub acted: Vec<usize>,
    /// `[slot, message]` for each environment whose policy raised or returned an action of
    /// another size (no action row).
    #[serde(default)]
    pub policy_errors: Vec<(usize, String)>,
    /// Values in the payload that follows (read by [`read_frame`] already).
    #[serde(default, rename = "payload")]
    _payload: usize,
}

/// What a reader needs of any header: how many payload values follow it.
#[derive(Deserialize)]
struct Announce {
    #[serde(default)]
    payload: usize,
}

/// A reply's header, read.
pub(super) fn parse_reply(header: &str) -> Result<Reply, String> {
    serde_json::from_str(header)
        .map_err(|e| format!("the header {} is not a reply ({e})", shown(header.as_bytes())))
}

/// Writes one frame (`header`: one line of JSON, without its end of line).
pub(super) fn write_frame(
    out: &mut impl Write,
    header: &str,
    payload: &[f32],
) -> std::io::Result<()> {
    out.write_all(header.as_bytes())?;
    out.write_all(b"\n")?;
    let bytes: Vec<u8> = payload.iter().flat_map(|v| v.to_le_bytes()).collect();
    out.write_all(&bytes)
}

/// Reads one frame: its header (without the end of line) and payload. `Err("")`: the stream ended
/// cleanly before a frame began; any other `Err` says why what came is not a frame.
pub(super) fn read_frame(input: &mut impl BufRead) -> Result<(String, Vec<f32>), String> {
    let mut line = Vec::new();
    let n = input
        .by_ref()
        .take(MAX_HEADER as u64)
        .read_until(b'\n', &mut line)
        .map_err(|e| format!("reading a header: {e}"))?;
    if n == 0 {
        return Err(String::new());
    }
    if line.last() != Some(&b'\n') {
        return Err(format!("a header of {n} bytes without its end of line: {}", shown(&line)));
    }
    let header = String::from_utf8(line)
        .map_err(|e| format!("a header that is not UTF-8: {}", shown(e.as_bytes())))?;
    let header = header.trim_end().to_owned();
    let announce: Announce = serde_json::from_str(&header)
        .map_err(|e| format!("the header {} is not a reply ({e})", shown(header.as_bytes())))?;
    let mut bytes = vec![0u8; announce.payload * 4];
    input.read_exact(&mut bytes).map_err(|e| {
        format!(
            "the header announced {} payload values, which did not come ({e})",
            announce.payload
        )
    })?;
    let values =
        bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    Ok((header, values))
}

/// The start of a header, for an error message.
fn shown(line: &[u8]) -> String {
    let text = String::from_utf8_lossy(line);
    let text = text.trim_end();
    match text.char_indices().nth(200) {
        Some((i, _)) => format!("`{}...`", &text[..i]),
        None => format!("`{text}`"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_round_trips_its_numbers_bit_for_bit() {
        let values = [1.5f32, -0.0, f32::MIN_POSITIVE, 3.0e38, 0.1];
        let mut buf = Vec::new();
        let header = serde_json::json!({"slots": [0, 2], "payload": values.len()}).to_string();
        write_frame(&mut buf, &header, &values).unwrap();
        let (header, got) = read_frame(&mut buf.as_slice()).unwrap();
        assert_eq!(parse_reply(&header).unwrap().slots, vec![0, 2]);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got), bits(&values));
    }

    #[test]
    fn a_garbled_stream_is_named_not_parsed() {
        let err = read_frame(&mut b"hello from a print\n".as_slice()).unwrap_err();
        let err2 = parse_reply("{\"slots\": [0], \"unknown\": 1}").unwrap_err();
        assert!(err2.contains("unknown field `unknown`"), "{err2}");
        assert!(err.contains("`hello from a print` is not a reply"), "{err}");
        let err = read_frame(&mut b"{\"payload\": 3}\n\x00\x00".as_slice()).unwrap_err();
        assert!(err.contains("announced 3 payload values"), "{err}");
        assert_eq!(read_frame(&mut b"".as_slice()).unwrap_err(), "");
        let err = read_frame(&mut b"{\"slots\": [1]".as_slice()).unwrap_err();
        assert!(err.contains("without its end of line"), "{err}");
    }
}
