//! Tracked points as CSV (`import csv`): one row per point per frame.
//!
//! The first line names the columns, in any order: `frame`, `point`, `x`, `y`, `z` (required)
//! and `u`, `v` (optional rest coordinates in metres); other columns are ignored. `frame` and
//! `point` are integers; a point appears at most once per frame. A point missing from a frame,
//! or given there with empty or `nan` coordinates, was not seen in it (an occluded or dropped
//! marker): the rollout's `visible` mask says so, and losses, fits and the motion RMSE skip it.
//! The points are every id of any frame; frames are taken in increasing order of `frame`,
//! points in increasing order of `point` (so `--pinned` counts points in that order: with ids
//! 0…N−1, the ids themselves). Without `u`, `v` the first frame must be flat, see every point and
//! gives the rest rectangle. Fields are separated by commas (or semicolons or tabs); lines
//! starting with `#` are skipped.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result, bail};

use super::{ImportOptions, ImportSummary, Motion, RestShape, rest_rectangle, write_rollout};

/// One point of one frame: its position (`None` where the point was not seen) and its line.
type Row = (Option<[f64; 3]>, usize);

/// Imports a CSV of tracked points as `<out>/<file stem>.npz`.
pub fn import_tracks(path: &Path, options: &ImportOptions) -> Result<ImportSummary> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let shown = path.display();
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let Some((_, header)) = lines.next() else {
        bail!("{shown} is empty");
    };
    let header = Header::parse(header, path)?;
    let mut tracks = Tracks::default();
    for (number, line) in lines {
        tracks.add(&header, number, line, path)?;
    }
    let Some((&first_frame, _)) = tracks.frames.iter().next() else {
        bail!("{shown} holds no rows");
    };
    let grid = Grid::new(&tracks.frames, path)?;
    let shape = tracks.rest_shape(&header, &grid.ids, path)?;
    let rect = rest_rectangle(&shape, options.size)?;
    let rest_from = if header.uv.is_some() {
        "the u, v columns".to_string()
    } else {
        format!("the flat frame {first_frame}")
    };
    let motion = Motion {
        name: super::stem(path),
        frames: tracks.frames.len(),
        points: grid.ids.len(),
        positions: grid.positions,
        visible: Some(grid.visible),
        triangles: None,
    };
    write_rollout(&motion, rect, &rest_from, options)
}

/// The header line: the separator and where each column is.
struct Header {
    /// The field separator.
    sep: char,
    /// The column names, lowercase.
    names: Vec<String>,
    /// The columns of `frame`, `point`, `x`, `y`, `z`.
    required: [usize; 5],
    /// The columns of `u` and `v`, when given.
    uv: Option<[usize; 2]>,
}

impl Header {
    /// Reads the header line of the CSV file at `path`; fails where a column is missing.
    fn parse(header: &str, path: &Path) -> Result<Self> {
        let shown = path.display();
        let sep = [',', ';', '\t']
            .into_iter()
            .find(|&c| header.contains(c))
            .unwrap_or(',');
        let names: Vec<String> = header
            .split(sep)
            .map(|s| s.trim().trim_matches('"').to_ascii_lowercase())
            .collect();
        let column = |name: &str| names.iter().position(|n| n == name);
        let mut required = [0usize; 5];
        for (slot, name) in required.iter_mut().zip(["frame", "point", "x", "y", "z"]) {
            *slot = column(name).ok_or_else(|| {
                anyhow::anyhow!(
                    "{shown}, line 1: no `{name}` column (the header must name frame, point, x, y, z; \
                     optionally u, v), found: {}",
                    names.join(", ")
                )
            })?;
        }
        let uv = match (column("u"), column("v")) {
            (Some(u), Some(v)) => Some([u, v]),
            (None, None) => None,
            _ => bail!("{shown}, line 1: give both `u` and `v` columns, or neither"),
        };
        Ok(Self {
            sep,
            names,
            required,
            uv,
        })
    }
}

/// The rows read so far.
#[derive(Default)]
struct Tracks {
    /// Per frame, per point: its row.
    frames: BTreeMap<i64, BTreeMap<i64, Row>>,
    /// Per point: its rest coordinates and the line that first gave them.
    rest: BTreeMap<i64, ([f64; 2], usize)>,
}

impl Tracks {
    /// Adds line `number` of the CSV file at `path`; fails on a malformed field, a point
    /// given twice in a frame, or rest coordinates that differ from the point's earlier ones.
    fn add(&mut self, header: &Header, number: usize, line: &str, path: &Path) -> Result<()> {
        let shown = path.display();
        let (names, required) = (&header.names, &header.required);
        let fields: Vec<&str> = line
            .split(header.sep)
            .map(|s| s.trim().trim_matches('"'))
            .collect();
        let field = |c: usize| -> Result<&str> {
            fields.get(c).copied().ok_or_else(|| {
                anyhow::anyhow!("{shown}, line {number}: missing column `{}`", names[c])
            })
        };
        let int = |c: usize| -> Result<i64> {
            let s = field(c)?;
            s.parse().map_err(|_| {
                anyhow::anyhow!(
                    "{shown}, line {number}: `{}` = `{s}` is not an integer",
                    names[c]
                )
            })
        };
        let num = |c: usize| -> Result<f64> {
            let s = field(c)?;
            let v: f64 = s.parse().map_err(|_| {
                anyhow::anyhow!(
                    "{shown}, line {number}: `{}` = `{s}` is not a number",
                    names[c]
                )
            })?;
            if !v.is_finite() || !(v as f32).is_finite() {
                bail!("{shown}, line {number}: `{}` = {s} is not finite", names[c]);
            }
            Ok(v)
        };
        let (frame, point) = (int(required[0])?, int(required[1])?);
        // Empty or `nan` coordinates: the point was not seen in this frame.
        let hidden = |c: usize| {
            fields
                .get(c)
                .is_some_and(|s| s.is_empty() || s.eq_ignore_ascii_case("nan"))
        };
        let p = if required[2..].iter().all(|&c| hidden(c)) {
            None
        } else {
            Some([num(required[2])?, num(required[3])?, num(required[4])?])
        };
        let rows = self.frames.entry(frame).or_default();
        if let Some((_, first)) = rows.insert(point, (p, number)) {
            bail!(
                "{shown}, line {number}: frame {frame}, point {point} was already given on line {first}"
            );
        }
        if let Some([u, v]) = header.uv {
            let q = [num(u)?, num(v)?];
            match self.rest.get(&point) {
                Some(&(old, line)) if old != q => bail!(
                    "{shown}, line {number}: point {point} has rest coordinates ({}, {}) here and \
                     ({}, {}) on line {line}",
                    q[0],
                    q[1],
                    old[0],
                    old[1]
                ),
                Some(_) => {}
                None => {
                    self.rest.insert(point, (q, number));
                }
            }
        }
        Ok(())
    }

    /// The rest shape of the points `ids`: their `u`, `v` columns, or else the first frame,
    /// which must see every point.
    fn rest_shape(&self, header: &Header, ids: &[i64], path: &Path) -> Result<RestShape> {
        let shown = path.display();
        if header.uv.is_some() {
            return Ok(RestShape::Given {
                uv: ids.iter().map(|id| self.rest[id].0).collect(),
                what: format!("{shown} (columns u, v)"),
            });
        }
        let (&first_frame, first) = self
            .frames
            .iter()
            .next()
            .expect("import_tracks refuses a file without rows");
        let mut reference = Vec::with_capacity(ids.len());
        for id in ids {
            match first.get(id) {
                Some((Some(p), _)) => reference.push(*p),
                _ => bail!(
                    "{shown}: frame {first_frame} does not see point {id}: without `u`, `v` \
                     columns the first frame gives the rest shape and must see every point"
                ),
            }
        }
        Ok(RestShape::Flat {
            reference,
            what: format!("{shown}, frame {first_frame}"),
        })
    }
}

/// Every point of every frame, in increasing order of `frame` and `point`.
struct Grid {
    /// The point ids of any frame.
    ids: Vec<i64>,
    /// Positions per frame and point (NaN where not seen).
    positions: Vec<f32>,
    /// Whether each point was seen in each frame.
    visible: Vec<bool>,
}

impl Grid {
    /// The rows laid out frame by frame; fails where a point is seen in no frame.
    fn new(frames: &BTreeMap<i64, BTreeMap<i64, Row>>, path: &Path) -> Result<Self> {
        let shown = path.display();
        let ids: Vec<i64> = frames
            .values()
            .flat_map(|points| points.keys().copied())
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect();
        let mut positions = Vec::with_capacity(frames.len() * ids.len() * 3);
        let mut visible = Vec::with_capacity(frames.len() * ids.len());
        for points in frames.values() {
            for id in &ids {
                let seen = points.get(id).and_then(|(p, _)| *p);
                visible.push(seen.is_some());
                positions.extend(seen.map_or([f32::NAN; 3], |p| p.map(|c| c as f32)));
            }
        }
        for (slot, id) in ids.iter().enumerate() {
            if !visible.iter().skip(slot).step_by(ids.len()).any(|&v| v) {
                bail!(
                    "{shown}: point {id} is seen in no frame (its coordinates are always missing)"
                );
            }
        }
        Ok(Self {
            ids,
            positions,
            visible,
        })
    }
}
