//! The line under each table of `RESULTS.md` that says what the registry holds for it: per cell
//! the archived seeds against the planned ones, and what a run took, read from the archives'
//! `provenance.json` (never typed into a manifest).

use std::collections::BTreeMap;

/// Per device name: each archived run's wall time (seconds) and how many runs shared the device.
pub(super) type Walls = BTreeMap<String, Vec<(f64, u32)>>;

/// The archive of a section, described from the registry: per planned cell (`planned`: its id and
/// how many seeds its budget plans), how many are archived (`seeds`) and what a run took
/// (`walls`; the manifest's budget note describes the plan only).
pub(super) fn text(
    planned: &[(String, usize)],
    seeds: &BTreeMap<String, Vec<u64>>,
    walls: &BTreeMap<String, Walls>,
) -> String {
    let mut full = Vec::new();
    let mut short = Vec::new();
    let mut none = Vec::new();
    for (id, n) in planned {
        let took = walls.get(id).map_or(String::new(), |w| format!("; {}", took_by_device(w)));
        match seeds.get(id).map_or(0, Vec::len) {
            0 => none.push(format!("`{id}`")),
            k if k >= *n => full.push(format!("`{id}` ({k}{took})")),
            k => short.push(format!("`{id}` ({k} of {n}{took})")),
        }
    }
    let list = |v: &[String]| if v.is_empty() { "none".to_string() } else { v.join(", ") };
    format!(
        "Archived (from the registry; per cell its seeds, a run's wall time and how many runs \
         shared its device): every planned seed for {}; fewer for {}; no run for {}.",
        list(&full),
        list(&short),
        list(&none)
    )
}

/// What the cell's runs took, per device where more than one ran them (a GPU's minutes and a
/// CPU's hours are no range).
fn took_by_device(walls: &Walls) -> String {
    match walls.len() {
        1 => walls.values().map(|w| took_text(w)).collect(),
        _ => walls
            .iter()
            .map(|(d, w)| format!("{} on {d}", took_text(w)))
            .collect::<Vec<_>>()
            .join("; "),
    }
}

/// The range of the runs' wall times and of how many runs shared the device: "24 min to 80 min,
/// 2 at once". A variant's time is its evaluation's (it trained nothing).
fn took_text(walls: &[(f64, u32)]) -> String {
    let (lo, hi) =
        walls.iter().fold((f64::INFINITY, 0.0f64), |(l, h), &(w, _)| (l.min(w), h.max(w)));
    let (a, b) = walls.iter().fold((u32::MAX, 0), |(l, h), &(_, n)| (l.min(n), h.max(n)));
    let time = match duration(lo) == duration(hi) {
        true => duration(lo),
        false => format!("{} to {}", duration(lo), duration(hi)),
    };
    let shared = match (a, b) {
        (1, 1) => "alone".to_string(),
        (a, b) if a == b => format!("{a} at once"),
        (a, b) => format!("{a} to {b} at once"),
    };
    format!("{time}, {shared}")
}

/// Seconds as a person reads a run's length: seconds below 2 minutes, minutes below 3 hours.
fn duration(s: f64) -> String {
    match s {
        s if s < 120.0 => format!("{s:.0} s"),
        s if s < 3.0 * 3600.0 => format!("{:.0} min", s / 60.0),
        s => format!("{:.1} h", s / 3600.0),
    }
}

#[cfg(test)]
mod tests {
    use super::{took_by_device, took_text};

    #[test]
    fn a_cells_run_time_is_the_range_of_its_archived_runs() {
        assert_eq!(
            took_text(&[(1423.0, 2), (4789.0, 2), (1876.0, 2)]),
            "24 min to 80 min, 2 at once"
        );
        assert_eq!(took_text(&[(45.4, 1)]), "45 s, alone");
        assert_eq!(took_text(&[(9000.0, 1), (14400.0, 2)]), "150 min to 4.0 h, 1 to 2 at once");
        assert_eq!(took_text(&[(600.0, 2), (610.0, 2)]), "10 min, 2 at once");
        let mut two = std::collections::BTreeMap::new();
        two.insert("cpu".to_string(), vec![(21000.0, 2)]);
        two.insert("gpu".to_string(), vec![(180.0, 4)]);
        assert_eq!(took_by_device(&two), "5.8 h, 2 at once on cpu; 3 min, 4 at once on gpu");
        two.remove("gpu");
        assert_eq!(took_by_device(&two), "5.8 h, 2 at once");
    }
}
