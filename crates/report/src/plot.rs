//! Learning-curve figures in the style of the paper's Figure 2: x = training iteration,
//! y = average return over the test tasks, one line per method (mean over seeds) with a shaded
//! ± std band.
//!
//! Both backends draw into memory (a pixel buffer, a String) so the files can be written
//! atomically by the caller, and so plotters' `image` dependency is not needed: the PNG is
//! encoded with the small `png` crate.

use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::FontStyle;

use crate::aggregate::{method_rank, EnvReport, MethodCurve, METHOD_ORDER};
use crate::error::ReportError;

pub(crate) const WIDTH: u32 = 800;
pub(crate) const HEIGHT: u32 = 500;
/// Width of the legend column right of the chart; the legend lives outside the plotting area
/// so it can never hide a curve.
const LEGEND_WIDTH: u32 = 190;
const FONT: &str = "sans-serif";

/// Embedded so that text renders the same everywhere, including CI machines without fonts.
static FONT_BYTES: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// plotters' ab_glyph font table is process-global; registering once is enough, and the
/// outcome is cached so every later call reports the same result.
fn ensure_font() -> Result<(), ReportError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, FONT_BYTES).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(ReportError::Font("assets/DejaVuSans.ttf is not a valid TrueType font".to_string()))
    }
}

/// Tableau-10 colours (matplotlib's default cycle), familiar from most RL papers' plots.
pub(crate) const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// Colours of an environment's curves, in order: fixed for the paper's methods (so a method
/// has the same colour in every figure), the remaining palette entries for other methods.
fn colors(curves: &[MethodCurve]) -> Vec<RGBColor> {
    let mut next_free = METHOD_ORDER.len();
    curves
        .iter()
        .map(|c| {
            let (rank, _) = method_rank(&c.method);
            let idx = if rank < METHOD_ORDER.len() {
                rank
            } else {
                next_free += 1;
                next_free - 1
            };
            PALETTE[idx % PALETTE.len()]
        })
        .collect()
}

/// Rendered figure: PNG bytes and SVG text.
pub(crate) struct Figure {
    pub png: Vec<u8>,
    pub svg: String,
}

/// One line of a figure: its legend name, colour and finite `(x, mean, std)` points.
pub(crate) struct Curve {
    pub name: String,
    pub color: RGBColor,
    pub points: Vec<(f64, f64, f64)>,
}

/// The words on a figure, so the same drawing code serves learning curves and per-task returns.
pub(crate) struct Labels {
    pub caption: String,
    pub x_desc: String,
    pub y_desc: String,
    /// Grey line under each curve's name in the legend, one per curve (e.g. its seed count).
    pub legend_sub: Vec<String>,
    /// Grey lines at the end of the legend saying what lines and bands mean.
    pub notes: Vec<String>,
}

/// How the x range is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum XAxis {
    /// Training iterations: start at 0 when the first evaluation is early, as in the paper.
    Iterations,
    /// Task indices: discrete, so half a task of air either side keeps the end markers whole.
    Tasks,
}

/// The learning curves of one environment.
pub(crate) fn render(env: &EnvReport, title: Option<&str>) -> Result<Figure, ReportError> {
    let curves: Vec<Curve> = env
        .curves
        .iter()
        .zip(colors(&env.curves))
        .map(|(c, color)| Curve { name: c.method.clone(), color, points: finite_points(c) })
        .collect();
    let labels =
        Labels {
            caption: match title {
                Some(t) => format!("{t}: {}", env.env),
                None => format!("{}: return on unseen test tasks", env.env),
            },
            x_desc: "Training iteration".to_string(),
            y_desc: "Average return on test tasks".to_string(),
            legend_sub: env
                .curves
                .iter()
                .map(|c| {
                    if c.n_seeds == 1 {
                        "1 seed".to_string()
                    } else {
                        format!("{} seeds", c.n_seeds)
                    }
                })
                .collect(),
            notes: vec!["line: mean over seeds".to_string(), "band: ± std over seeds".to_string()],
        };
    render_figure(
        &curves,
        &labels,
        XAxis::Iterations,
        &format!("the learning curves of {}", env.env),
        &format!("curves_{}.png", env.file_stem),
    )
}

/// Draws `curves` into a PNG and an SVG. `what` names the figure in a drawing error, `png_name`
/// the file in an encoding error.
pub(crate) fn render_figure(
    curves: &[Curve],
    labels: &Labels,
    x_axis: XAxis,
    what: &str,
    png_name: &str,
) -> Result<Figure, ReportError> {
    ensure_font()?;
    let plot_err = |message: String| ReportError::Plot { figure: what.to_string(), message };

    let mut pixels = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (WIDTH, HEIGHT)).into_drawing_area();
        draw(&root, curves, labels, x_axis).map_err(plot_err)?;
    }
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, HEIGHT)).into_drawing_area();
        draw(&root, curves, labels, x_axis).map_err(plot_err)?;
    }
    let png =
        encode_png(&pixels).map_err(|source| ReportError::Png { path: png_name.into(), source })?;
    Ok(Figure { png, svg })
}

fn encode_png(rgb: &[u8]) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, WIDTH, HEIGHT);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header()?;
    writer.write_image_data(rgb)?;
    writer.finish()?;
    Ok(out)
}

fn pe<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

/// Finite (iteration, mean, std) triples of a curve; non-finite points (a diverged seed) cannot
/// be placed on an axis and are left to the CSV.
fn finite_points(c: &MethodCurve) -> Vec<(f64, f64, f64)> {
    c.points
        .iter()
        .filter(|p| p.stat.mean.is_finite())
        .map(|p| {
            let std = if p.stat.std.is_finite() { p.stat.std } else { 0.0 };
            (p.iteration as f64, p.stat.mean, std)
        })
        .collect()
}

/// Axis ranges covering every line and band, with a little air so nothing touches the frame.
fn ranges(curves: &[&[(f64, f64, f64)]], x_axis: XAxis) -> ((f64, f64), (f64, f64)) {
    let pts = curves.iter().copied().flatten();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, m, s) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(m - s);
        y1 = y1.max(m + s);
    }
    if x0 > x1 {
        return ((0.0, 1.0), (0.0, 1.0));
    }
    let pad = if y1 - y0 > 0.0 { 0.06 * (y1 - y0) } else { y0.abs().max(1.0) * 0.1 };
    if x_axis == XAxis::Tasks {
        return ((x0 - 0.5, x1 + 0.5), (y0 - pad, y1 + pad));
    }
    // Start at 0 like the paper's plots when the first evaluation is early in training; a late
    // start (a resumed or zoomed run) keeps its own range.
    if x0 > 0.0 && x0 <= 0.25 * x1 {
        x0 = 0.0;
    }
    if x1 - x0 < 1.0 {
        // A single evaluation: give it a visible neighbourhood.
        x0 -= 1.0;
        x1 += 1.0;
    } else {
        // Keep markers at the last evaluation from being cut in half by the frame.
        x1 += 0.02 * (x1 - x0);
    }
    ((x0, x1), (y0 - pad, y1 + pad))
}

/// Decimals for y tick labels: enough to tell neighbouring ticks apart (plotters places about
/// eight), no more.
fn y_decimals(span: f64) -> usize {
    let step = span / 8.0;
    if !(step.is_finite() && step > 0.0) || step >= 1.0 {
        return 0;
    }
    (-step.log10()).ceil().clamp(0.0, 6.0) as usize
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    curves: &[Curve],
    labels: &Labels,
    x_axis: XAxis,
) -> Result<(), String> {
    root.fill(&WHITE).map_err(pe)?;
    let body = root.titled(&labels.caption, (FONT, 22).into_font().color(&BLACK)).map_err(pe)?;
    let (chart_area, legend_area) = body.split_horizontally(WIDTH - LEGEND_WIDTH);

    let series: Vec<&[(f64, f64, f64)]> = curves.iter().map(|c| c.points.as_slice()).collect();
    let ((x0, x1), (y0, y1)) = ranges(&series, x_axis);
    let decimals = y_decimals(y1 - y0);

    let mut chart = ChartBuilder::on(&chart_area)
        .margin(10)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(pe)?;
    // Iterations are integers: a fractional tick (short x ranges) gets no label rather than a
    // rounded duplicate of its neighbour's.
    let x_fmt =
        |x: &f64| if (x - x.round()).abs() < 1e-6 { format!("{x:.0}") } else { String::new() };
    let y_fmt = move |y: &f64| format!("{y:.decimals$}");
    chart
        .configure_mesh()
        .x_desc(labels.x_desc.as_str())
        .y_desc(labels.y_desc.as_str())
        .axis_desc_style((FONT, 16))
        .label_style((FONT, 13))
        .x_labels(8)
        .y_labels(8)
        .x_label_formatter(&x_fmt)
        .y_label_formatter(&y_fmt)
        .bold_line_style(RGBColor(225, 225, 225))
        .light_line_style(TRANSPARENT)
        .axis_style(RGBColor(90, 90, 90))
        .draw()
        .map_err(pe)?;

    // Bands first, so that every mean line is drawn on top of every band.
    for (pts, color) in series.iter().zip(curves.iter().map(|c| c.color)) {
        if pts.len() < 2 {
            continue;
        }
        let upper = pts.iter().map(|&(x, m, s)| (x, m + s));
        let lower = pts.iter().rev().map(|&(x, m, s)| (x, m - s));
        let outline: Vec<(f64, f64)> = upper.chain(lower).collect();
        chart
            .draw_series(std::iter::once(Polygon::new(outline, color.mix(0.2).filled())))
            .map_err(pe)?;
    }
    for (pts, color) in series.iter().zip(curves.iter().map(|c| c.color)) {
        chart
            .draw_series(LineSeries::new(
                pts.iter().map(|&(x, m, _)| (x, m)),
                color.stroke_width(2),
            ))
            .map_err(pe)?;
        // Markers only while they stay readable; they make sparse or single evaluations
        // visible, and a lone point gets an error bar in place of a band.
        if pts.len() <= 30 {
            chart
                .draw_series(pts.iter().map(|&(x, m, _)| Circle::new((x, m), 3, color.filled())))
                .map_err(pe)?;
        }
        if let [(x, m, s)] = pts {
            let (x, m, s) = (*x, *m, *s);
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(x, m - s), (x, m + s)],
                    color.stroke_width(2),
                )))
                .map_err(pe)?;
        }
    }

    draw_legend(&legend_area, curves, labels)?;
    root.present().map_err(pe)?;
    Ok(())
}

/// Legend column: a colour swatch and the curve's name, its sub-line below it in grey, and
/// notes on what line and band mean.
fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    curves: &[Curve],
    labels: &Labels,
) -> Result<(), String> {
    let sub_style = TextStyle::from((FONT, 12).into_font())
        .color(&RGBColor(110, 110, 110))
        .pos(Pos::new(HPos::Left, VPos::Center));
    let text_x = 42;
    let room = LEGEND_WIDTH.saturating_sub(text_x as u32 + 4);
    let mut y = 30;
    for (i, c) in curves.iter().enumerate() {
        let color = c.color;
        area.draw(&Rectangle::new([(8, y - 6), (34, y + 6)], color.mix(0.2).filled()))
            .map_err(pe)?;
        area.draw(&PathElement::new(vec![(8, y), (34, y)], color.stroke_width(3))).map_err(pe)?;
        let (name, name_style) = fit_label(area, &c.name, room)?;
        area.draw(&Text::new(name, (text_x, y), name_style)).map_err(pe)?;
        if let Some(sub) = labels.legend_sub.get(i) {
            area.draw(&Text::new(sub.as_str(), (text_x, y + 17), sub_style.clone())).map_err(pe)?;
        }
        y += 44;
    }
    y += 6;
    for line in &labels.notes {
        area.draw(&Text::new(line.as_str(), (8, y), sub_style.clone())).map_err(pe)?;
        y += 17;
    }
    Ok(())
}

/// A method name that fits the legend column: the normal size if it fits, else a smaller size,
/// else shortened with an ellipsis (the full name is in the CSV files and the table).
fn fit_label<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    name: &str,
    room: u32,
) -> Result<(String, TextStyle<'static>), String> {
    let style = |size: u32| {
        TextStyle::from((FONT, size).into_font())
            .color(&BLACK)
            .pos(Pos::new(HPos::Left, VPos::Center))
    };
    let fits = |text: &str, st: &TextStyle<'static>| -> Result<bool, String> {
        Ok(area.estimate_text_size(text, st).map_err(pe)?.0 <= room)
    };
    for size in [15, 13, 12] {
        let st = style(size);
        if fits(name, &st)? {
            return Ok((name.to_string(), st));
        }
    }
    let st = style(12);
    let mut chars: Vec<char> = name.chars().collect();
    while !chars.is_empty() {
        chars.pop();
        let short: String = chars.iter().collect::<String>() + "…";
        if fits(&short, &st)? {
            return Ok((short, st));
        }
    }
    Ok(("…".to_string(), st))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_pad_degenerate_data() {
        let ((x0, x1), (y0, y1)) = ranges(&[&[(10.0, 5.0, 0.0)]], XAxis::Iterations);
        assert!(x0 < 10.0 && x1 > 10.0);
        assert!(y0 < 5.0 && y1 > 5.0);
    }

    #[test]
    fn tick_decimals_follow_the_step() {
        assert_eq!(y_decimals(45.0), 0);
        assert_eq!(y_decimals(5.0), 1);
        assert_eq!(y_decimals(0.4), 2);
        assert_eq!(y_decimals(0.0), 0);
    }

    fn curve(method: &str) -> MethodCurve {
        MethodCurve { method: method.to_string(), n_seeds: 1, points: Vec::new() }
    }

    #[test]
    fn paper_methods_keep_their_colour() {
        let a = colors(&[curve("mt-orl")]);
        let b = colors(&[curve("prompt-dt"), curve("x"), curve("mt-orl"), curve("y")]);
        assert_eq!(a[0], b[2]);
        // Other methods take distinct colours not used by the paper's methods.
        assert_ne!(b[1], b[3]);
        assert!(!colors(&[
            curve("prompt-dt"),
            curve("prompt-mt-bc"),
            curve("mt-orl"),
            curve("mt-bc-finetune"),
            curve("macaw")
        ])
        .contains(&b[1]));
    }
}
