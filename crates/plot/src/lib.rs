//! Plotting primitives for reports and figures: spring and triangle maps on the rest sheet,
//! line plots, predicted-versus-true scatters, histograms, and PNG/GIF output.
//!
//! Every figure is drawn with [plotters] into an RGB buffer and encoded with the `png` or `gif`
//! crate. Text uses DejaVu Sans embedded in the binary (no system fonts). The `*_png` functions
//! write one figure each; the `draw_*` functions draw one panel into a drawing area, so that
//! several panels can share an image (see [`render`] and [`write_png`]).
//!
//! Colour maps are viridis (dark purple = low, yellow = high) with a labelled colour bar; pass
//! the same range to maps that are to be compared.
#![warn(missing_docs)]

use std::io::BufWriter;
use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Result, anyhow, bail};
use plotters::chart::MeshStyle;
use plotters::coord::Shift;
use plotters::coord::ranged1d::ValueFormatter;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;

use springtime_core::cloth::{SpringFamily, Topology};

pub mod anim;

/// A drawing area on an RGB bitmap: one panel of a figure.
pub type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

/// A chart with linear axes on a panel.
type Chart<'b, 'a> =
    ChartContext<'b, BitMapBackend<'a>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Size of one map panel, pixels.
pub const MAP_PANEL: (u32, u32) = (360, 360);
/// Width of a colour bar beside maps, pixels.
pub const COLORBAR_WIDTH: u32 = 110;
/// Size of one line plot, pixels.
pub const PLOT_PANEL: (u32, u32) = (560, 400);

/// Font family used for all text (DejaVu Sans, registered on first use).
const FONT: &str = "sans-serif";

/// Series colours (Matplotlib's tab10).
pub const PALETTE: [RGBColor; 10] = [
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

fn fonts() -> Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok()
            && plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold()).is_ok()
    });
    if !ok {
        bail!("cannot load the embedded DejaVu Sans font");
    }
    Ok(())
}

fn err(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("drawing failed: {e}")
}

/// Draws the series' legend at `position`, in the one style every figure shares.
fn draw_legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
    position: SeriesLabelPosition,
) -> Result<()> {
    chart
        .configure_series_labels()
        .position(position)
        .label_font(text(12))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(180, 180, 180))
        .draw()
        .map_err(err)
}

/// A text style of `size` pixels (rounded up to an even size: plotters' glyph placement
/// rounds half pixels unevenly at odd sizes, which lifts full stops off the baseline).
pub fn text(size: u32) -> TextStyle<'static> {
    let size = size + size % 2;
    (FONT, size as f64).into_font().color(&BLACK)
}

/// The viridis colour of `t` in `[0, 1]` (clamped; NaN gives grey).
pub fn viridis(t: f64) -> RGBColor {
    if t.is_nan() {
        return RGBColor(160, 160, 160);
    }
    ViridisRGB::get_color(t.clamp(0.0, 1.0))
}

/// A value range `(lo, hi)` covering every finite value of `sets`, widened when it is empty
/// or a single point (so a colour bar always has extent).
pub fn value_range(sets: &[&[f64]]) -> (f64, f64) {
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for v in sets.iter().flat_map(|s| s.iter()).filter(|v| v.is_finite()) {
        lo = lo.min(*v);
        hi = hi.max(*v);
    }
    if !(lo <= hi) {
        return (0.0, 1.0);
    }
    widen((lo, hi))
}

fn widen((lo, hi): (f64, f64)) -> (f64, f64) {
    if hi - lo > 1e-9 * hi.abs().max(lo.abs()).max(1e-300) {
        return (lo, hi);
    }
    let pad = (0.05 * lo.abs()).max(1e-6);
    (lo - pad, hi + pad)
}

/// Renders a `width × height` image: `draw` gets the whole white canvas. Returns RGB bytes.
pub fn render(
    width: u32,
    height: u32,
    draw: impl for<'a> FnOnce(&Area<'a>) -> Result<()>,
) -> Result<Vec<u8>> {
    fonts()?;
    let mut buf = vec![255u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        draw(&root)?;
        root.present().map_err(err)?;
    }
    Ok(buf)
}

/// Encodes RGB bytes as a PNG file, atomically.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    springtime_core::io::write_atomic(path, |file| {
        let mut enc = png::Encoder::new(BufWriter::new(file), width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(png::Compression::Balanced);
        let mut w = enc.write_header()?;
        w.write_image_data(rgb)?;
        w.finish()?;
        Ok(())
    })
}

/// Renders and writes a PNG in one call.
pub fn png_figure(
    path: &Path,
    width: u32,
    height: u32,
    draw: impl for<'a> FnOnce(&Area<'a>) -> Result<()>,
) -> Result<()> {
    let rgb = render(width, height, draw)?;
    write_png(path, width, height, &rgb)
}

/// Writes an animated GIF from RGB frames of one size; `delays_cs[i]` is frame `i`'s display
/// time in hundredths of a second. Loops forever.
pub fn write_gif(
    path: &Path,
    width: u32,
    height: u32,
    frames: &[Vec<u8>],
    delays_cs: &[u16],
) -> Result<()> {
    let (w, h) = (
        u16::try_from(width).map_err(|_| anyhow!("GIF width {width} is too large"))?,
        u16::try_from(height).map_err(|_| anyhow!("GIF height {height} is too large"))?,
    );
    springtime_core::io::write_atomic(path, |file| {
        let mut enc = gif::Encoder::new(BufWriter::new(file), w, h, &[])?;
        enc.set_repeat(gif::Repeat::Infinite)?;
        for (i, rgb) in frames.iter().enumerate() {
            let mut frame = gif::Frame::from_rgb_speed(w, h, rgb, 10);
            frame.delay = delays_cs.get(i).copied().unwrap_or(4);
            enc.write_frame(&frame)?;
        }
        Ok(())
    })
}

/// Height of the title strip that [`title`] takes, pixels.
pub const TITLE_HEIGHT: u32 = 30;

/// Writes `caption` centred in a [`TITLE_HEIGHT`]-pixel strip at the top of `area` and returns
/// the rest of the area.
pub fn title<'a>(area: &Area<'a>, caption: &str, size: u32) -> Result<Area<'a>> {
    let (top, rest) = area.split_vertically(TITLE_HEIGHT);
    draw_centred(&top, caption, text(size))?;
    Ok(rest)
}

/// Draws `caption` and, in the middle of the panel, `message` (a panel with nothing to show
/// says so instead of drawing empty axes).
pub fn draw_message(area: &Area, caption: &str, message: &str) -> Result<()> {
    let area = title(area, caption, 16)?;
    draw_centred(&area, message, text(14).color(&RGBColor(90, 90, 90)))
}

/// Draws `s` in `style` centred in `area`.
fn draw_centred(area: &Area, s: &str, style: TextStyle) -> Result<()> {
    use plotters::style::text_anchor::{HPos, Pos, VPos};
    let (w, h) = area.dim_in_pixel();
    let style = style.pos(Pos::new(HPos::Center, VPos::Center));
    area.draw(&Text::new(
        s.to_string(),
        (w as i32 / 2, h as i32 / 2),
        style,
    ))
    .map_err(err)?;
    Ok(())
}

/// Extends `(x, y)` ranges so that one unit is as long on both axes in a plotting box of
/// `px × py` pixels.
fn equal_aspect(
    (mut x0, mut x1): (f64, f64),
    (mut y0, mut y1): (f64, f64),
    (px, py): (f64, f64),
) -> ((f64, f64), (f64, f64)) {
    let (wx, wy) = (x1 - x0, y1 - y0);
    let scale = (wx / px).max(wy / py);
    let (ex, ey) = (scale * px - wx, scale * py - wy);
    x0 -= ex / 2.0;
    x1 += ex / 2.0;
    y0 -= ey / 2.0;
    y1 += ey / 2.0;
    ((x0, x1), (y0, y1))
}

const MAP_CAPTION: u32 = 16;
const MAP_X_LABELS: u32 = 30;
const MAP_Y_LABELS: u32 = 42;
const MAP_MARGIN: u32 = 8;

/// Builds a chart over the rest rectangle `[0, width] × [0, height]` with equal aspect, axes
/// in metres and `caption` on top.
fn sheet_chart<'a, 'b>(
    area: &'b Area<'a>,
    width: f64,
    height: f64,
    caption: &str,
) -> Result<
    ChartContext<
        'b,
        BitMapBackend<'a>,
        Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
    >,
> {
    let (w, h) = area.dim_in_pixel();
    let pad = 0.04 * width.max(height);
    let px = w as f64 - (MAP_Y_LABELS + 2 * MAP_MARGIN) as f64;
    let py = h as f64 - (MAP_X_LABELS + 2 * MAP_MARGIN + MAP_CAPTION + 10) as f64;
    let ((x0, x1), (y0, y1)) = equal_aspect(
        (-pad, width + pad),
        (-pad, height + pad),
        (px.max(10.0), py.max(10.0)),
    );
    let mut chart = ChartBuilder::on(area)
        .caption(caption, text(MAP_CAPTION))
        .margin(MAP_MARGIN)
        .x_label_area_size(MAP_X_LABELS)
        .y_label_area_size(MAP_Y_LABELS)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_labels(5)
        .y_labels(5)
        .x_desc("u (m)")
        .y_desc("v (m)")
        .label_style(text(12))
        .axis_desc_style(text(12))
        .draw()
        .map_err(err)?;
    Ok(chart)
}

/// Rest endpoints of spring `s` as drawn on a map: shortened a little so that springs meeting
/// at a particle stay distinct, and bending springs (which overlap their neighbours along a
/// line) offset sideways by their phase along the line, so that every spring is visible.
fn drawn_segment(topology: &Topology, s: usize) -> [(f64, f64); 2] {
    let [a, b] = topology.springs[s];
    let (pa, pb) = (topology.rest_uv[a], topology.rest_uv[b]);
    let (dx, dy) = (pb[0] - pa[0], pb[1] - pa[1]);
    let len = (dx * dx + dy * dy).sqrt().max(1e-12);
    let h = topology.spacing();
    let shrink = (0.12 * h).min(0.2 * len);
    let (ux, uy) = (dx / len, dy / len);
    let mut off = (0.0, 0.0);
    if let (SpringFamily::Bending, Some([nx, _])) = (topology.family[s], topology.grid) {
        // Grid row and column of each end.
        let ((ra, ca), (rb, cb)) = ((a / nx, a % nx), (b / nx, b % nx));
        let (phase, stride) = if ra == rb {
            (ca.min(cb), ca.abs_diff(cb))
        } else {
            (ra.min(rb), ra.abs_diff(rb))
        };
        if stride > 1 {
            let k = (phase % stride) as f64 - (stride - 1) as f64 / 2.0;
            let gap = 0.3 * h / stride as f64;
            off = (-uy * k * gap, ux * k * gap);
        }
    }
    [
        (pa[0] + ux * shrink + off.0, pa[1] + uy * shrink + off.1),
        (pb[0] - ux * shrink + off.0, pb[1] - uy * shrink + off.1),
    ]
}

/// What a map panel draws on the rest rectangle, one value per element, coloured on viridis.
#[derive(Debug, Clone, Copy)]
pub enum Map<'a> {
    /// Springs as segments between their rest endpoints, slightly shortened; bending springs,
    /// which overlap along a line, are offset sideways by their phase. `family` selects one
    /// family (structural, shear or bending; `None`: every spring).
    Springs {
        /// The springs and their rest positions.
        topology: &'a Topology,
        /// The one family drawn, or all.
        family: Option<SpringFamily>,
    },
    /// Filled triangles (e.g. an FEM source's stiffness map).
    Triangles {
        /// Vertex positions on the rest rectangle, metres.
        rest_uv: &'a [[f64; 2]],
        /// Vertex indices, one triple per triangle.
        triangles: &'a [[usize; 3]],
    },
    /// A filled square around each particle of a grid topology (a cell of the grid spacing).
    Particles {
        /// The particles and their rest positions.
        topology: &'a Topology,
    },
}

impl Map<'_> {
    /// How many values the map takes, and what they are of.
    fn elements(&self) -> (usize, &'static str) {
        match self {
            Map::Springs { topology, .. } => (topology.num_springs(), "springs"),
            Map::Triangles { triangles, .. } => (triangles.len(), "triangles"),
            Map::Particles { topology } => (topology.num_particles(), "particles"),
        }
    }

    /// The rest rectangle's width and height, metres.
    fn extent(&self) -> (f64, f64) {
        match self {
            Map::Springs { topology, .. } | Map::Particles { topology } => {
                (topology.width, topology.height)
            }
            Map::Triangles { rest_uv, .. } => {
                let (w, h) = rest_uv
                    .iter()
                    .fold((0f64, 0f64), |(w, h), p| (w.max(p[0]), h.max(p[1])));
                (w.max(1e-9), h.max(1e-9))
            }
        }
    }
}

/// Draws `map` with `values` (one per element; NaN grey) coloured on viridis over `range`,
/// under `caption`. No colour bar: see [`draw_colorbar`].
pub fn draw_map(
    area: &Area,
    map: Map,
    values: &[f64],
    caption: &str,
    range: (f64, f64),
) -> Result<()> {
    let (n, noun) = map.elements();
    if values.len() != n {
        bail!("{} values for {n} {noun}", values.len());
    }
    if let Map::Triangles { rest_uv, triangles } = map
        && let Some(t) = triangles
            .iter()
            .find(|t| t.iter().any(|&i| i >= rest_uv.len()))
    {
        bail!(
            "triangle {t:?} indexes past the {} rest positions",
            rest_uv.len()
        );
    }
    let (w, h) = map.extent();
    let mut chart = sheet_chart(area, w, h, caption)?;
    let (lo, hi) = widen(range);
    let color = |v: f64| viridis((v - lo) / (hi - lo));
    match map {
        Map::Springs { topology, family } => {
            draw_springs(area, &mut chart, topology, family, values, color)?
        }
        Map::Triangles { rest_uv, triangles } => {
            chart
                .draw_series(triangles.iter().zip(values).map(|(t, &v)| {
                    let pts: Vec<(f64, f64)> =
                        t.iter().map(|&i| (rest_uv[i][0], rest_uv[i][1])).collect();
                    Polygon::new(pts, color(v).filled())
                }))
                .map_err(err)?;
        }
        Map::Particles { topology } => {
            let (hx, hy) = match topology.grid {
                Some([nx, ny]) => (
                    topology.width / (nx - 1).max(1) as f64 / 2.0,
                    topology.height / (ny - 1).max(1) as f64 / 2.0,
                ),
                None => (topology.spacing() / 2.0, topology.spacing() / 2.0),
            };
            chart
                .draw_series(topology.rest_uv.iter().zip(values).map(|(p, &v)| {
                    Rectangle::new(
                        [(p[0] - hx, p[1] - hy), (p[0] + hx, p[1] + hy)],
                        color(v).filled(),
                    )
                }))
                .map_err(err)?;
        }
    }
    Ok(())
}

/// The springs of [`Map::Springs`], with a line width from the grid spacing on screen.
fn draw_springs(
    area: &Area,
    chart: &mut Chart,
    topology: &Topology,
    family: Option<SpringFamily>,
    values: &[f64],
    color: impl Fn(f64) -> RGBColor,
) -> Result<()> {
    let (x_px, _) = chart.plotting_area().dim_in_pixel();
    let xr = chart.x_range();
    let px_per_m = x_px as f64 / (xr.end - xr.start);
    let h = topology.spacing();
    // Structural springs alone do not overlap: they can be drawn wide enough to read on fine
    // grids; with the diagonals in the same panel, thinner.
    let width = match family {
        Some(SpringFamily::Bending) => (0.10 * h * px_per_m).clamp(1.0, 4.0),
        Some(SpringFamily::Structural) => (0.35 * h * px_per_m).clamp(2.0, 10.0),
        _ => (0.13 * h * px_per_m).clamp(1.0, 5.0),
    } as u32;
    let shown: Vec<usize> = (0..topology.num_springs())
        .filter(|&s| family.is_none_or(|f| topology.family[s] == f))
        .collect();
    if shown.is_empty() {
        let c = chart.plotting_area().dim_in_pixel();
        area.draw(&Text::new(
            "no springs of this family",
            (c.0 as i32 / 3, c.1 as i32 / 2),
            text(14),
        ))
        .map_err(err)?;
        return Ok(());
    }
    chart
        .draw_series(shown.iter().map(|&s| {
            PathElement::new(
                drawn_segment(topology, s).to_vec(),
                color(values[s]).stroke_width(width),
            )
        }))
        .map_err(err)?;
    Ok(())
}

/// Draws a vertical viridis colour bar over `range` with ticks and the quantity's `label`.
/// Sized to sit beside [`MAP_PANEL`]-high maps.
pub fn draw_colorbar(area: &Area, range: (f64, f64), label: &str) -> Result<()> {
    let (lo, hi) = widen(range);
    let mut chart = ChartBuilder::on(area)
        .margin_top(MAP_MARGIN + MAP_CAPTION + 10)
        .margin_bottom(MAP_MARGIN + MAP_X_LABELS)
        .margin_left(4)
        .margin_right(4)
        .y_label_area_size(62)
        .build_cartesian_2d(0f64..1f64, lo..hi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .y_labels(7)
        .y_label_formatter(&|v| tick(*v))
        .y_desc(label)
        .label_style(text(12))
        .axis_desc_style(text(12))
        .draw()
        .map_err(err)?;
    let n = 200;
    let d = (hi - lo) / n as f64;
    chart
        .draw_series((0..n).map(|i| {
            let y = lo + i as f64 * d;
            Rectangle::new(
                [(0.0, y), (1.0, y + d)],
                viridis((i as f64 + 0.5) / n as f64).filled(),
            )
        }))
        .map_err(err)?;
    Ok(())
}

/// A compact tick label: at most 3 significant digits without trailing zeros, scientific
/// outside `[1e-3, 1e5)`.
pub fn tick(v: f64) -> String {
    let a = v.abs();
    if a < 1e-12 {
        return "0".into();
    }
    if !(1e-3..1e5).contains(&a) {
        let s = format!("{v:.1e}");
        return s.replace(".0e", "e");
    }
    let decimals = (2 - a.log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// Writes one map with a colour bar.
///
/// - `values`: one per element of `map` (e.g. learned `k` in N/m per spring);
/// - `range`: the colour range `(lo, hi)`; give two maps the same range to compare them (see
///   [`value_range`]); values outside are clamped;
/// - `label`: the colour bar's label, with units (e.g. `"k (N/m)"`).
pub fn map_png(
    path: &Path,
    map: Map,
    values: &[f64],
    title: &str,
    range: (f64, f64),
    label: &str,
) -> Result<()> {
    let (w, h) = MAP_PANEL;
    png_figure(path, w + COLORBAR_WIDTH, h, |root| {
        let (panel, bar) = root.split_horizontally(w);
        draw_map(&panel, map, values, title, range)?;
        draw_colorbar(&bar, range, label)
    })
}

/// Writes a grid of spring maps sharing one colour range and colour bar: one row per entry of
/// `rows` (`(row name, values per spring)`, e.g. learned and true), one column per spring
/// family present in `topology` (structural, shear, bending). Panel captions read
/// `"<row name>: <family>"`.
pub fn spring_maps_png(
    path: &Path,
    topology: &Topology,
    rows: &[(&str, &[f64])],
    title: &str,
    range: (f64, f64),
    label: &str,
) -> Result<()> {
    let rows: Vec<MapRow> = rows
        .iter()
        .map(|&(name, values)| MapRow {
            name,
            values,
            range,
            label,
        })
        .collect();
    spring_map_rows_png(path, topology, &rows, title)
}

/// One row of [`spring_map_rows_png`]: a quantity per spring with its own colour range and
/// colour-bar label.
#[derive(Debug, Clone, Copy)]
pub struct MapRow<'a> {
    /// Row name, the start of each panel's caption.
    pub name: &'a str,
    /// One value per spring (NaN is drawn grey).
    pub values: &'a [f64],
    /// Colour range `(lo, hi)`.
    pub range: (f64, f64),
    /// Colour-bar label, with units.
    pub label: &'a str,
}

/// Writes a grid of spring maps: one row per entry of `rows`, each with its own colour range
/// and colour bar (e.g. two quantities of different units), one column per spring family
/// present in `topology`. [`spring_maps_png`] is the case of one shared range.
pub fn spring_map_rows_png(
    path: &Path,
    topology: &Topology,
    rows: &[MapRow],
    title: &str,
) -> Result<()> {
    let families: Vec<SpringFamily> = [
        SpringFamily::Structural,
        SpringFamily::Shear,
        SpringFamily::Bending,
    ]
    .into_iter()
    .filter(|f| topology.family.contains(f))
    .collect();
    let (pw, ph) = MAP_PANEL;
    let head = TITLE_HEIGHT;
    let (w, h) = (
        pw * families.len() as u32 + COLORBAR_WIDTH,
        head + ph * rows.len() as u32,
    );
    png_figure(path, w, h, |root| {
        let body = self::title(root, title, 18)?;
        let (maps, bar) = body.split_horizontally(pw * families.len() as u32);
        let cells = maps.split_evenly((rows.len(), families.len()));
        for (r, row) in rows.iter().enumerate() {
            for (c, &fam) in families.iter().enumerate() {
                draw_map(
                    &cells[r * families.len() + c],
                    Map::Springs {
                        topology,
                        family: Some(fam),
                    },
                    row.values,
                    &format!("{}: {}", row.name, fam.name()),
                    row.range,
                )?;
            }
        }
        let bars = bar.split_evenly((rows.len(), 1));
        for (b, row) in bars.iter().zip(rows) {
            draw_colorbar(b, row.range, row.label)?;
        }
        Ok(())
    })
}

/// Writes the curvature elements' stiffness `kappa` (one per element of `topology.curvature`)
/// as particle maps, each element drawn at its middle particle, one panel per direction (along
/// the rows, the columns, the main and the anti diagonal), one colour range; particles that are
/// the middle of no element of a direction grey.
pub fn curvature_map_png(
    path: &Path,
    topology: &Topology,
    kappa: &[f64],
    title: &str,
) -> Result<()> {
    if kappa.len() != topology.curvature.len() {
        bail!(
            "{} values for {} curvature elements",
            kappa.len(),
            topology.curvature.len()
        );
    }
    const DIRECTIONS: [&str; 4] = [
        "along rows",
        "along columns",
        "main diagonal",
        "anti diagonal",
    ];
    let p = topology.num_particles();
    let mut panels = vec![vec![f64::NAN; p]; DIRECTIONS.len()];
    let tol = 1e-9 * topology.width.max(topology.height).max(1.0);
    for (&[i, j, l], &v) in topology.curvature.iter().zip(kappa) {
        let (du, dv) = (
            topology.rest_uv[l][0] - topology.rest_uv[i][0],
            topology.rest_uv[l][1] - topology.rest_uv[i][1],
        );
        let direction = if dv.abs() < tol {
            0
        } else if du.abs() < tol {
            1
        } else if du * dv > 0.0 {
            2
        } else {
            3
        };
        panels[direction][j] = v;
    }
    let shown: Vec<(&str, &Vec<f64>)> = DIRECTIONS
        .iter()
        .zip(&panels)
        .filter(|(_, v)| v.iter().any(|x| x.is_finite()))
        .map(|(d, v)| (*d, v))
        .collect();
    let range = value_range(&[kappa]);
    let (pw, ph) = MAP_PANEL;
    let n = shown.len().max(1) as u32;
    png_figure(path, n * pw + COLORBAR_WIDTH, TITLE_HEIGHT + ph, |root| {
        let body = self::title(root, title, 18)?;
        let (maps, bar) = body.split_horizontally(n * pw);
        let cells = maps.split_evenly((1, n as usize));
        for (cell, (name, values)) in cells.iter().zip(&shown) {
            draw_map(cell, Map::Particles { topology }, values, name, range)?;
        }
        draw_colorbar(&bar, range, "κ (N/m)")
    })
}

/// One named curve of a line plot.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend entry.
    pub label: String,
    /// `(x, y)` points in order of `x`.
    pub points: Vec<(f64, f64)>,
    /// Colour (default: the series' place in [`PALETTE`]).
    pub color: Option<RGBColor>,
    /// Line width in pixels.
    pub width: u32,
}

impl Series {
    /// A series from a label and points.
    pub fn new(label: impl Into<String>, points: Vec<(f64, f64)>) -> Self {
        Self {
            label: label.into(),
            points,
            color: None,
            width: 2,
        }
    }

    /// The same series with lines `width` pixels wide.
    pub fn with_width(mut self, width: u32) -> Self {
        self.width = width;
        self
    }

    /// The same series in `color`.
    pub fn with_color(mut self, color: RGBColor) -> Self {
        self.color = Some(color);
        self
    }
}

/// The house style of a chart's grid and labels (light grey lines, 12-pt labels, 14-pt axis
/// descriptions).
fn house_mesh<'m, 'a, 'b, X: Ranged, Y: Ranged, DB: DrawingBackend>(
    mesh: &'m mut MeshStyle<'a, 'b, X, Y, DB>,
) -> &'m mut MeshStyle<'a, 'b, X, Y, DB> {
    mesh.label_style(text(12))
        .axis_desc_style(text(14))
        .light_line_style(RGBColor(235, 235, 235))
        .bold_line_style(RGBColor(215, 215, 215))
}

/// Draws the house grid and axes with [`tick`] labels: the axes' descriptions `(x, y)`, 6 labels
/// on x and `y_labels` on y (linear or log).
fn draw_axes<'a: 'b, 'b, Y>(
    chart: &mut ChartContext<'b, BitMapBackend<'a>, Cartesian2d<RangedCoordf64, Y>>,
    (x_desc, y_desc): (&str, &str),
    y_labels: usize,
) -> Result<()>
where
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    house_mesh(
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc(y_desc)
            .x_labels(6)
            .y_labels(y_labels)
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v)),
    )
    .draw()
    .map_err(err)
}

/// Draws a line plot of `series` (colours from [`PALETTE`], in order) with a legend.
/// `log_y` puts y on a log scale and drops points with `y ≤ 0`; non-finite points are dropped
/// either way. `marks` are vertical lines at the given x with a label to their right at the
/// bottom (e.g. pass boundaries).
pub fn draw_curves(
    area: &Area,
    caption: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
    log_y: bool,
    marks: &[(f64, &str)],
) -> Result<()> {
    let keep = |&(x, y): &(f64, f64)| x.is_finite() && y.is_finite() && (!log_y || y > 0.0);
    let pts: Vec<Vec<(f64, f64)>> = series
        .iter()
        .map(|s| s.points.iter().copied().filter(keep).collect())
        .collect();
    let all: Vec<(f64, f64)> = pts.iter().flatten().copied().collect();
    if all.is_empty() {
        return draw_message(area, caption, "no data to plot");
    }
    let (x0, x1) = widen(all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.0), a.1.max(p.0))
    }));
    let (y0, y1) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.1), a.1.max(p.1))
    });
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(caption, text(16))
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(if log_y { 62 } else { 70 });
    let panel = CurvesPanel {
        x_label,
        y_label,
        series,
        pts,
        log_y,
        marks,
    };
    if log_y {
        let (lo, hi) = (y0 / 1.5, y1 * 1.5);
        panel.finish(
            builder
                .build_cartesian_2d(x0..x1, (lo..hi).log_scale())
                .map_err(err)?,
        )
    } else {
        let (lo, hi) = widen((y0.min(0.0), y1));
        let pad = 0.05 * (hi - lo);
        panel.finish(
            builder
                .build_cartesian_2d(x0..x1, lo..hi + pad)
                .map_err(err)?,
        )
    }
}

/// What [`draw_curves`] draws once its chart is built: axis descriptions, the series with
/// their drawable points, and the vertical marks.
struct CurvesPanel<'s> {
    x_label: &'s str,
    y_label: &'s str,
    series: &'s [Series],
    /// The points of each series that can be drawn (finite, and positive on a log scale).
    pts: Vec<Vec<(f64, f64)>>,
    log_y: bool,
    marks: &'s [(f64, &'s str)],
}

impl CurvesPanel<'_> {
    /// The line style of series `i`.
    fn line(&self, i: usize) -> ShapeStyle {
        self.series[i]
            .color
            .unwrap_or(PALETTE[i % PALETTE.len()])
            .stroke_width(self.series[i].width)
    }

    /// Draws the grid, the marks, the series and the legend on `chart` (linear or log y).
    fn finish<'a: 'b, 'b, Y>(
        &self,
        mut chart: ChartContext<'b, BitMapBackend<'a>, Cartesian2d<RangedCoordf64, Y>>,
    ) -> Result<()>
    where
        Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
    {
        draw_axes(&mut chart, (self.x_label, self.y_label), 8)?;
        let yr = chart.y_range();
        for &(x, name) in self.marks {
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(x, yr.start), (x, yr.end)],
                    RGBColor(120, 120, 120).stroke_width(1),
                )))
                .map_err(err)?;
            chart
                .draw_series(std::iter::once(
                    EmptyElement::at((x, yr.start))
                        + Text::new(
                            name.to_string(),
                            (4, -18),
                            text(12).color(&RGBColor(90, 90, 90)),
                        ),
                ))
                .map_err(err)?;
        }
        for (i, (s, p)) in self.series.iter().zip(&self.pts).enumerate() {
            // A series with nothing to draw keeps its legend entry, saying so.
            let label = if p.is_empty() {
                format!(
                    "{} (no {}values: not drawn)",
                    s.label,
                    if self.log_y { "positive " } else { "" }
                )
            } else {
                s.label.clone()
            };
            let line = self.line(i);
            chart
                .draw_series(LineSeries::new(p.iter().copied(), line))
                .map_err(err)?
                .label(label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], line));
        }
        draw_legend(&mut chart, SeriesLabelPosition::UpperRight)?;
        Ok(())
    }
}

/// Writes a line plot of several curves with a legend ([`PLOT_PANEL`] pixels).
///
/// - `series`: the curves, coloured in order from [`PALETTE`];
/// - `log_y`: log-scale y axis (points with `y ≤ 0` are dropped), else linear from 0 or the
///   lowest value.
pub fn curves_png(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
    log_y: bool,
) -> Result<()> {
    let (w, h) = PLOT_PANEL;
    png_figure(path, w, h, |root| {
        draw_curves(root, title, x_label, y_label, series, log_y, &[])
    })
}

/// Draws predicted against true values as points with the identity line: one point per item,
/// coloured by `groups[i]` (index into `group_names` and [`PALETTE`]). Both axes share one
/// range so that the identity is the diagonal.
pub fn draw_truth_scatter(
    area: &Area,
    caption: &str,
    quantity: &str,
    truth: &[f64],
    predicted: &[f64],
    groups: &[usize],
    group_names: &[&str],
) -> Result<()> {
    let (lo, hi) = value_range(&[truth, predicted]);
    let pad = 0.06 * (hi - lo);
    let (lo, hi) = (lo - pad, hi + pad);
    let mut chart = ChartBuilder::on(area)
        .caption(caption, text(16))
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(62)
        .build_cartesian_2d(lo..hi, lo..hi)
        .map_err(err)?;
    let descs = (format!("true {quantity}"), format!("learned {quantity}"));
    draw_axes(&mut chart, (&descs.0, &descs.1), 6)?;
    chart
        .draw_series(std::iter::once(PathElement::new(
            vec![(lo, lo), (hi, hi)],
            BLACK.stroke_width(1),
        )))
        .map_err(err)?
        .label("identity (learned = true)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(1)));
    for (g, name) in group_names.iter().enumerate() {
        let color = PALETTE[g % PALETTE.len()];
        let pts: Vec<(f64, f64)> = truth
            .iter()
            .zip(predicted)
            .zip(groups)
            .filter(|(_, gg)| **gg == g)
            .map(|((t, p), _)| (*t, *p))
            .collect();
        if pts.is_empty() {
            continue;
        }
        chart
            .draw_series(
                pts.iter()
                    .map(|&p| Circle::new(p, 3, color.mix(0.45).filled())),
            )
            .map_err(err)?
            .label(*name)
            .legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
    }
    draw_legend(&mut chart, SeriesLabelPosition::UpperLeft)?;
    Ok(())
}

/// Draws a histogram of `values` (one colour per group, stacked) with `bins` bins.
pub fn draw_histogram(
    area: &Area,
    caption: &str,
    quantity: &str,
    values: &[f64],
    groups: &[usize],
    group_names: &[&str],
    bins: usize,
) -> Result<()> {
    let bins = bins.max(1);
    let (lo, hi) = value_range(&[values]);
    let width = (hi - lo) / bins as f64;
    let mut counts = vec![vec![0usize; bins]; group_names.len().max(1)];
    for (v, &g) in values.iter().zip(groups) {
        if v.is_finite() && g < counts.len() {
            let i = (((v - lo) / width) as usize).min(bins - 1);
            counts[g][i] += 1;
        }
    }
    let top = (0..bins)
        .map(|i| counts.iter().map(|c| c[i]).sum::<usize>())
        .max()
        .unwrap_or(0)
        .max(1) as f64;
    let mut chart = ChartBuilder::on(area)
        .caption(caption, text(16))
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(55)
        .build_cartesian_2d(lo..hi, 0f64..top * 1.4) // headroom for the legend
        .map_err(err)?;
    house_mesh(
        chart
            .configure_mesh()
            .x_desc(quantity.to_string())
            .y_desc("springs")
            .x_labels(6)
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| format!("{v:.0}")),
    )
    .draw()
    .map_err(err)?;
    let mut base = vec![0usize; bins];
    for (g, name) in group_names.iter().enumerate() {
        let color = PALETTE[g % PALETTE.len()];
        let rects: Vec<_> = (0..bins)
            .filter(|&i| counts[g][i] > 0)
            .map(|i| {
                let x = lo + i as f64 * width;
                let (b, t) = (base[i] as f64, (base[i] + counts[g][i]) as f64);
                Rectangle::new([(x, b), (x + width, t)], color.filled())
            })
            .collect();
        for i in 0..bins {
            base[i] += counts[g][i];
        }
        if rects.is_empty() {
            continue;
        }
        chart
            .draw_series(rects)
            .map_err(err)?
            .label(*name)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], color.filled()));
    }
    draw_legend(&mut chart, SeriesLabelPosition::UpperRight)?;
    Ok(())
}

/// A band of values over x: `(x, low, middle, high)` per point.
pub type Band = Vec<(f64, f64, f64, f64)>;

/// Draws thin lines for `members` (e.g. each test rollout), a shaded band between the band's
/// low and high and a bold line through its middle (e.g. the mean), with a legend.
#[allow(clippy::too_many_arguments)]
pub fn draw_band(
    area: &Area,
    caption: &str,
    x_label: &str,
    y_label: &str,
    members: &[Vec<(f64, f64)>],
    band: &Band,
    names: (&str, &str, &str),
) -> Result<()> {
    let ys = band
        .iter()
        .flat_map(|b| [b.1, b.3])
        .chain(members.iter().flatten().map(|p| p.1))
        .filter(|v| v.is_finite());
    let hi = ys.fold(0f64, f64::max);
    let (x0, x1) = widen(
        band.iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |a, b| {
                (a.0.min(b.0), a.1.max(b.0))
            }),
    );
    let (x0, x1) = if x0.is_finite() { (x0, x1) } else { (0.0, 1.0) };
    let hi = if hi > 0.0 { hi * 1.08 } else { 1.0 };
    let mut chart = ChartBuilder::on(area)
        .caption(caption, text(16))
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(70)
        .build_cartesian_2d(x0..x1, 0f64..hi)
        .map_err(err)?;
    draw_axes(&mut chart, (x_label, y_label), 8)?;
    let shade = PALETTE[0].mix(0.22);
    if !band.is_empty() {
        let mut poly: Vec<(f64, f64)> = band.iter().map(|b| (b.0, b.3)).collect();
        poly.extend(band.iter().rev().map(|b| (b.0, b.1)));
        chart
            .draw_series(std::iter::once(Polygon::new(poly, shade.filled())))
            .map_err(err)?
            .label(names.1)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 20, y + 5)], shade.filled()));
    }
    let thin = RGBColor(150, 150, 150).stroke_width(1);
    for (i, m) in members.iter().enumerate() {
        let s = chart
            .draw_series(LineSeries::new(m.iter().copied(), thin))
            .map_err(err)?;
        if i == 0 {
            s.label(names.2)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], thin));
        }
    }
    let bold = PALETTE[0].stroke_width(2);
    chart
        .draw_series(LineSeries::new(band.iter().map(|b| (b.0, b.2)), bold))
        .map_err(err)?
        .label(names.0)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], bold));
    draw_legend(&mut chart, SeriesLabelPosition::UpperLeft)?;
    Ok(())
}

/// Distinct values of `truth` (to 6 significant digits), sorted.
pub fn levels(truth: &[f64]) -> Vec<f64> {
    let mut v: Vec<f64> = truth.iter().copied().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    v.dedup_by(|a, b| (*a - *b).abs() <= 1e-6 * a.abs().max(b.abs()));
    v
}

/// Draws learned values per true level (for ground truth with a few distinct values, such as
/// the stiffness stripes of a source): one column of points per level and group (e.g. spring
/// family), spread sideways so that points do not hide each other, a red line at the true
/// value of each level and a black tick at the mean of each column.
pub fn draw_level_strips(
    area: &Area,
    caption: &str,
    quantity: &str,
    truth: &[f64],
    learned: &[f64],
    groups: &[usize],
    group_names: &[&str],
) -> Result<()> {
    let layout = StripLayout::new(truth, groups, group_names.len());
    let lv = &layout.levels;
    let (lo, hi) = value_range(&[truth, learned]);
    let pad = 0.06 * (hi - lo);
    let n = lv.len().max(1);
    // Headroom above the data for the legend.
    let mut chart = ChartBuilder::on(area)
        .caption(caption, text(16))
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(62)
        .build_cartesian_2d(-0.5f64..n as f64 - 0.5, lo - pad..hi + 0.45 * (hi - lo))
        .map_err(err)?;
    let names: Vec<String> = lv.iter().map(|&l| tick(l)).collect();
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(n)
        .x_label_formatter(&|v| {
            let i = v.round();
            if (v - i).abs() < 1e-6 && i >= 0.0 && (i as usize) < names.len() {
                names[i as usize].clone()
            } else {
                String::new()
            }
        })
        .y_labels(8)
        .y_label_formatter(&|v| tick(*v))
        .x_desc(format!("true {quantity}"))
        .y_desc(format!("learned {quantity}"))
        .label_style(text(12))
        .axis_desc_style(text(14))
        .light_line_style(RGBColor(240, 240, 240))
        .bold_line_style(RGBColor(220, 220, 220))
        .draw()
        .map_err(err)?;
    let strips = LevelStrips {
        layout: &layout,
        truth,
        learned,
        groups,
    };
    strips.draw_points(&mut chart, group_names)?;
    let red = RGBColor(215, 25, 28).stroke_width(2);
    chart
        .draw_series(
            lv.iter().enumerate().map(|(i, &l)| {
                PathElement::new(vec![(i as f64 - 0.45, l), (i as f64 + 0.45, l)], red)
            }),
        )
        .map_err(err)?
        .label("true value")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], red));
    chart
        .draw_series(strips.means())
        .map_err(err)?
        .label("mean of the column")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(2)));
    draw_legend(&mut chart, SeriesLabelPosition::UpperLeft)?;
    Ok(())
}

/// The columns of [`draw_level_strips`]: the true levels, the groups present, and where each
/// level's column for each group sits.
struct StripLayout {
    /// Distinct true values, sorted (see [`levels`]).
    levels: Vec<f64>,
    /// Groups with at least one value, in order.
    present: Vec<usize>,
    /// Half the width of one column.
    half: f64,
}

impl StripLayout {
    fn new(truth: &[f64], groups: &[usize], n_groups: usize) -> Self {
        let levels = levels(truth);
        let present: Vec<usize> = (0..n_groups).filter(|g| groups.contains(g)).collect();
        let half = 0.32 / present.len().max(1) as f64;
        Self {
            levels,
            present,
            half,
        }
    }

    /// The index of the level that true value `t` belongs to.
    fn level_of(&self, t: f64) -> usize {
        self.levels
            .iter()
            .position(|l| (l - t).abs() <= 1e-6 * l.abs().max(t.abs()))
            .unwrap_or(0)
    }

    /// The sideways offset of group `g`'s column from its level.
    fn slot(&self, g: usize) -> f64 {
        let present = &self.present;
        let i = present.iter().position(|&p| p == g).unwrap_or(0) as f64;
        (i - (present.len() as f64 - 1.0) / 2.0) * 0.8 / present.len().max(1) as f64
    }

    /// A fixed pseudo-random spread per spring (no dependence on the run or the platform).
    fn spread(&self, i: usize) -> f64 {
        let h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11;
        (h as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * self.half
    }
}

/// The values that [`draw_level_strips`] draws, laid out in columns.
struct LevelStrips<'s> {
    layout: &'s StripLayout,
    truth: &'s [f64],
    learned: &'s [f64],
    groups: &'s [usize],
}

impl LevelStrips<'_> {
    /// Draws one column of points per level and group, each group with its legend entry.
    fn draw_points(&self, chart: &mut Chart, group_names: &[&str]) -> Result<()> {
        let (layout, truth, learned) = (self.layout, self.truth, self.learned);
        for &g in &layout.present {
            let color = PALETTE[g % PALETTE.len()];
            let pts: Vec<(f64, f64)> = (0..truth.len().min(learned.len()))
                .filter(|&i| self.groups.get(i) == Some(&g) && learned[i].is_finite())
                .map(|i| {
                    (
                        layout.level_of(truth[i]) as f64 + layout.slot(g) + layout.spread(i),
                        learned[i],
                    )
                })
                .collect();
            chart
                .draw_series(
                    pts.iter()
                        .map(|&p| Circle::new(p, 2, color.mix(0.5).filled())),
                )
                .map_err(err)?
                .label(group_names[g])
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
        }
        Ok(())
    }

    /// A black tick at the mean of each non-empty column.
    fn means(&self) -> Vec<PathElement<(f64, f64)>> {
        let (layout, truth, learned) = (self.layout, self.truth, self.learned);
        let half = layout.half;
        let mut means = Vec::new();
        for li in 0..layout.levels.len() {
            for &g in &layout.present {
                let v: Vec<f64> = (0..truth.len().min(learned.len()))
                    .filter(|&i| self.groups.get(i) == Some(&g) && layout.level_of(truth[i]) == li)
                    .map(|i| learned[i])
                    .filter(|x| x.is_finite())
                    .collect();
                if !v.is_empty() {
                    let m = v.iter().sum::<f64>() / v.len() as f64;
                    let x = li as f64 + layout.slot(g);
                    means.push(PathElement::new(
                        vec![(x - half * 1.3, m), (x + half * 1.3, m)],
                        BLACK.stroke_width(2),
                    ));
                }
            }
        }
        means
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_short() {
        assert_eq!(tick(0.0), "0");
        assert_eq!(tick(20.0), "20");
        assert_eq!(tick(4.5), "4.5");
        assert_eq!(tick(0.015), "0.015");
        assert_eq!(tick(0.1), "0.1");
        assert_eq!(tick(1e-4), "1e-4");
        assert_eq!(tick(2.5e-5), "2.5e-5");
        assert_eq!(tick(123456.0), "1.2e5");
        assert_eq!(tick(-50.0), "-50");
    }

    #[test]
    fn ranges_cover_the_values_and_never_collapse() {
        assert_eq!(value_range(&[&[1.0, 3.0], &[2.0, f64::NAN]]), (1.0, 3.0));
        let (lo, hi) = value_range(&[&[6.0, 6.0]]);
        assert!(lo < 6.0 && hi > 6.0);
        assert_eq!(value_range(&[&[]]), (0.0, 1.0));
        assert_eq!(
            levels(&[10.0, 50.0, 10.0, 100.0, 50.000001]),
            vec![10.0, 50.0, 100.0]
        );
    }

    #[test]
    fn viridis_runs_from_purple_to_yellow() {
        assert_eq!(viridis(0.0), RGBColor(68, 1, 84));
        assert_eq!(viridis(1.0), RGBColor(254, 232, 37));
        assert_eq!(viridis(2.0), viridis(1.0));
    }
}
