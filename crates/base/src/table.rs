//! Tables for reports, written by one writer: Markdown (reports, benchmark and reproduction
//! summaries) and aligned plain text (terminal listings).

/// How a column's cells line up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Align {
    Left,
    Right,
}

/// How the Markdown rule under the header is spaced. Both render the same; the two spellings are
/// kept so reports already written (and diffs against them) stay byte for byte the same.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rule {
    /// `| --- | ---: |`
    Spaced,
    /// `|---|---:|`
    Tight,
}

/// A table: a header, one alignment per column, and rows of cells (already formatted).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Table {
    pub header: Vec<String>,
    pub align: Vec<Align>,
    pub rows: Vec<Vec<String>>,
}

impl Table {
    /// A table with `header`; the first column left-aligned, the others right-aligned (numbers).
    pub fn new(header: Vec<String>) -> Self {
        let align = (0..header.len()).map(|i| if i == 0 { Align::Left } else { Align::Right });
        Self { align: align.collect(), header, rows: Vec::new() }
    }

    /// A table with `header` and the alignment of each column given.
    pub fn with_align(header: Vec<String>, align: Vec<Align>) -> Self {
        Self { header, align, rows: Vec::new() }
    }

    /// Appends a row.
    pub fn push(&mut self, row: Vec<String>) {
        self.rows.push(row);
    }

    /// The table as Markdown: header, rule, rows, each line ending in `\n`.
    pub fn markdown(&self, rule: Rule) -> String {
        let mut out = markdown_row(&self.header);
        out.push('\n');
        out.push_str(&markdown_rule(&self.align, rule));
        out.push('\n');
        for row in &self.rows {
            out.push_str(&markdown_row(row));
            out.push('\n');
        }
        out
    }

    /// The table as aligned plain text: columns padded to their widest cell (in characters) and
    /// separated by two spaces, a rule of dashes under the header, trailing spaces trimmed.
    pub fn aligned_text(&self) -> String {
        let mut widths: Vec<usize> = self.header.iter().map(|h| h.chars().count()).collect();
        for row in &self.rows {
            for (w, cell) in widths.iter_mut().zip(row) {
                *w = (*w).max(cell.chars().count());
            }
        }
        let line = |cells: &[String]| -> String {
            let parts: Vec<String> = cells
                .iter()
                .zip(widths.iter().zip(&self.align))
                .map(|(cell, (&w, a))| match a {
                    Align::Left => format!("{cell:<w$}"),
                    Align::Right => format!("{cell:>w$}"),
                })
                .collect();
            parts.join("  ").trim_end().to_string()
        };
        let mut out = line(&self.header);
        out.push('\n');
        let rule: Vec<String> = widths.iter().map(|&w| "-".repeat(w)).collect();
        out.push_str(&rule.join("  "));
        out.push('\n');
        for row in &self.rows {
            out.push_str(&line(row));
            out.push('\n');
        }
        out
    }
}

/// One Markdown table line, without its newline: `| a | b |`. An empty cell is written as
/// `|  |` (a space either side of nothing).
pub fn markdown_row<S: AsRef<str>>(cells: &[S]) -> String {
    let cells: Vec<&str> = cells.iter().map(AsRef::as_ref).collect();
    format!("| {} |", cells.join(" | "))
}

/// The Markdown rule under a header, without its newline.
pub fn markdown_rule(align: &[Align], rule: Rule) -> String {
    let marks: Vec<&str> = align
        .iter()
        .map(|a| match a {
            Align::Left => "---",
            Align::Right => "---:",
        })
        .collect();
    match rule {
        Rule::Spaced => markdown_row(&marks),
        Rule::Tight => format!("|{}|", marks.join("|")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn markdown_in_both_rule_styles() {
        let mut t = Table::new(strings(&["name", "n"]));
        t.push(strings(&["a", "1"]));
        t.push(strings(&["", "22"]));
        assert_eq!(
            t.markdown(Rule::Spaced),
            "| name | n |\n| --- | ---: |\n| a | 1 |\n|  | 22 |\n"
        );
        assert_eq!(t.markdown(Rule::Tight), "| name | n |\n|---|---:|\n| a | 1 |\n|  | 22 |\n");
    }

    #[test]
    fn aligned_text_pads_by_characters_and_trims() {
        let mut t = Table::with_align(
            strings(&["file", "n", "note"]),
            vec![Align::Left, Align::Right, Align::Left],
        );
        t.push(strings(&["ä.pkl", "10", ""]));
        t.push(strings(&["long-name", "2", "x"]));
        assert_eq!(
            t.aligned_text(),
            "file        n  note\n---------  --  ----\nä.pkl      10\nlong-name   2  x\n"
        );
    }
}
