//! Drawing cloth states in 3-D: a fixed oblique projection of particle positions, edges as
//! thin lines, pinned points in red; used for the rollout animation and its key frames.

use anyhow::Result;
use plotters::prelude::*;

use crate::{Area, Chart, text};

/// A fixed oblique orthographic view: the scene turned by `azimuth` about the vertical (z)
/// axis, then tilted by `elevation` towards the viewer. Angles in radians.
#[derive(Debug, Clone, Copy)]
pub struct View {
    /// Rotation about z.
    pub azimuth: f64,
    /// Tilt of the view above the horizontal plane.
    pub elevation: f64,
}

impl Default for View {
    /// 35° round, 25° above the horizon (z up, gravity along −z).
    fn default() -> Self {
        Self {
            azimuth: 35f64.to_radians(),
            elevation: 25f64.to_radians(),
        }
    }
}

impl View {
    /// Screen coordinates (right, up) of a point.
    pub fn project(&self, p: [f32; 3]) -> (f64, f64) {
        let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
        let (sa, ca) = self.azimuth.sin_cos();
        let (se, ce) = self.elevation.sin_cos();
        let right = x * ca - y * sa;
        let depth = x * sa + y * ca;
        (right, z * ce + depth * se)
    }

    /// Screen bounding box `((x0, x1), (y0, y1))` of flat `[.., 3]` position arrays.
    pub fn bounds<'a>(
        &self,
        sets: impl IntoIterator<Item = &'a [f32]>,
    ) -> ((f64, f64), (f64, f64)) {
        let mut b = (
            (f64::INFINITY, f64::NEG_INFINITY),
            (f64::INFINITY, f64::NEG_INFINITY),
        );
        for set in sets {
            for p in set.chunks_exact(3) {
                let (x, y) = self.project([p[0], p[1], p[2]]);
                if x.is_finite() && y.is_finite() {
                    b.0 = (b.0.0.min(x), b.0.1.max(x));
                    b.1 = (b.1.0.min(y), b.1.1.max(y));
                }
            }
        }
        if !(b.0.0 <= b.0.1) {
            return ((0.0, 1.0), (0.0, 1.0));
        }
        b
    }
}

/// Points to draw in one panel: positions `[N, 3]` (flat), edges between them, pinned flags.
#[derive(Debug, Clone, Copy)]
pub struct Layer<'a> {
    /// Positions, flat `[N, 3]`.
    pub positions: &'a [f32],
    /// Edges drawn as thin lines.
    pub edges: &'a [[usize; 2]],
    /// Pinned points, drawn red (empty: none).
    pub pinned: &'a [bool],
    /// Colour of points and edges.
    pub color: RGBColor,
    /// Point radius in pixels (0: no points).
    pub radius: u32,
}

/// Draws `layers` (in order, later on top) in the fixed `view`, within screen `bounds` (see
/// [`View::bounds`]) scaled to the panel with equal aspect; `caption` on top, a small x/y/z
/// triad in the lower left corner.
pub fn draw_cloth(
    area: &Area,
    caption: &str,
    view: &View,
    bounds: ((f64, f64), (f64, f64)),
    layers: &[Layer],
) -> Result<()> {
    let ((cx0, cx1), (cy0, cy1)) = window(area.dim_in_pixel(), bounds);
    let mut chart = ChartBuilder::on(area)
        .caption(caption, text(14))
        .margin(8)
        .build_cartesian_2d(cx0..cx1, cy0..cy1)
        .map_err(crate::err)?;
    chart
        .plotting_area()
        .fill(&RGBColor(250, 250, 250))
        .map_err(crate::err)?;
    for layer in layers {
        draw_layer(&mut chart, view, layer)?;
    }
    draw_triad(&mut chart, view, (cx0, cx1), (cy0, cy1))
}

/// The chart range `((x0, x1), (y0, y1))` that shows screen `bounds` with a margin and equal
/// aspect in a panel of `(w, h)` pixels.
fn window((w, h): (u32, u32), bounds: ((f64, f64), (f64, f64))) -> ((f64, f64), (f64, f64)) {
    let ((x0, x1), (y0, y1)) = bounds;
    let span = (x1 - x0).max(y1 - y0).max(1e-9);
    let pad = 0.05 * span;
    let (px, py) = (w as f64 - 16.0, h as f64 - 40.0);
    let (wx, wy) = (x1 - x0 + 2.0 * pad, y1 - y0 + 2.0 * pad);
    let scale = (wx / px).max(wy / py);
    let (ex, ey) = (scale * px - wx, scale * py - wy);
    let (cx0, cx1) = (x0 - pad - ex / 2.0, x1 + pad + ex / 2.0);
    let (cy0, cy1) = (y0 - pad - ey / 2.0, y1 + pad + ey / 2.0);
    ((cx0, cx1), (cy0, cy1))
}

/// Draws one layer's edges, then its points (pinned ones red and a pixel larger).
fn draw_layer(chart: &mut Chart, view: &View, layer: &Layer) -> Result<()> {
    let pt = |i: usize| {
        let p = &layer.positions[i * 3..i * 3 + 3];
        view.project([p[0], p[1], p[2]])
    };
    let n = layer.positions.len() / 3;
    chart
        .draw_series(
            layer
                .edges
                .iter()
                .filter(|[a, b]| *a < n && *b < n)
                .map(|&[a, b]| PathElement::new(vec![pt(a), pt(b)], layer.color.stroke_width(1))),
        )
        .map_err(crate::err)?;
    if layer.radius > 0 {
        chart
            .draw_series((0..n).map(|i| {
                let pinned = layer.pinned.get(i).copied().unwrap_or(false);
                let (c, r) = if pinned {
                    (RGBColor(215, 25, 28), layer.radius + 1)
                } else {
                    (layer.color, layer.radius)
                };
                Circle::new(pt(i), r, c.filled())
            }))
            .map_err(crate::err)?;
    }
    Ok(())
}

/// Draws the axis triad in the lower left corner of the chart range `(cx0, cx1) × (cy0, cy1)`:
/// unit directions projected, fixed length on screen.
fn draw_triad(
    chart: &mut Chart,
    view: &View,
    (cx0, cx1): (f64, f64),
    (cy0, cy1): (f64, f64),
) -> Result<()> {
    let origin = (cx0 + 0.09 * (cx1 - cx0), cy0 + 0.09 * (cy1 - cy0));
    let len = 0.08 * (cx1 - cx0).min(cy1 - cy0);
    for (axis, name, color) in [
        ([1.0, 0.0, 0.0], "x", RGBColor(200, 60, 60)),
        ([0.0, 1.0, 0.0], "y", RGBColor(40, 150, 40)),
        ([0.0, 0.0, 1.0], "z", RGBColor(50, 90, 200)),
    ] {
        let (dx, dy) = view.project(axis);
        let end = (origin.0 + len * dx, origin.1 + len * dy);
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![origin, end],
                color.stroke_width(2),
            )))
            .map_err(crate::err)?;
        chart
            .draw_series(std::iter::once(Text::new(
                name,
                (origin.0 + 1.25 * len * dx, origin.1 + 1.25 * len * dy),
                text(12).color(&color),
            )))
            .map_err(crate::err)?;
    }
    Ok(())
}
