//! PNG charts for the examples (plotters, with a font from `epaint_default_fonts`, so
//! nothing is needed from the system): panels of line series on linear or log axes.
//! Included by the examples with `#[path = "support/chart.rs"] mod chart;`.
#![allow(dead_code)]

use plotters::prelude::*;
use std::path::Path;

/// One line (optionally with markers) of a panel.
pub struct Series {
    /// Legend text.
    pub label: String,
    /// Points (x, y) in data units; non-finite or, on a log axis, non-positive values are
    /// left out.
    pub points: Vec<(f64, f64)>,
    /// Colour index (a fixed palette).
    pub color: usize,
    /// Draw markers at the points.
    pub markers: bool,
    /// Draw a line through the points.
    pub line: bool,
}

/// One chart.
pub struct Panel {
    /// Title above the chart.
    pub title: String,
    /// X axis label.
    pub x_label: String,
    /// Y axis label.
    pub y_label: String,
    /// Logarithmic x axis.
    pub x_log: bool,
    /// Logarithmic y axis.
    pub y_log: bool,
    /// The lines.
    pub series: Vec<Series>,
}

const PALETTE: [RGBColor; 11] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
    RGBColor(0, 0, 0),
];

fn font() {
    use std::sync::Once;
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        );
    });
}

fn axis(v: f64, log: bool) -> Option<f64> {
    if !v.is_finite() || (log && v <= 0.0) {
        None
    } else if log {
        Some(v.log10())
    } else {
        Some(v)
    }
}

fn label(v: f64, log: bool) -> String {
    let x = if log { 10f64.powf(v) } else { v };
    if x == 0.0 {
        "0".into()
    } else if x.abs() >= 1e4 || x.abs() < 1e-2 {
        format!("{x:.1e}")
    } else if x.abs() >= 10.0 || (x - x.round()).abs() < 1e-9 {
        format!("{x:.0}")
    } else {
        format!("{x:.2}")
    }
}

/// Draws `panels` in a grid of `cols` columns into a PNG at `path`, each panel
/// `panel_size` pixels.
pub fn draw(
    path: &Path,
    panels: &[Panel],
    cols: usize,
    panel_size: (u32, u32),
) -> Result<(), String> {
    font();
    let cols = cols.max(1);
    let rows = panels.len().div_ceil(cols).max(1);
    let size = (panel_size.0 * cols as u32, panel_size.1 * rows as u32);
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let areas = root.split_evenly((rows, cols));
    for (panel, area) in panels.iter().zip(areas.iter()) {
        let pts: Vec<Vec<(f64, f64)>> = panel
            .series
            .iter()
            .map(|s| {
                s.points
                    .iter()
                    .filter_map(|&(x, y)| Some((axis(x, panel.x_log)?, axis(y, panel.y_log)?)))
                    .collect()
            })
            .collect();
        let all: Vec<(f64, f64)> = pts.iter().flatten().copied().collect();
        if all.is_empty() {
            continue;
        }
        let (mut x0, mut x1, mut y0, mut y1) = all.iter().fold(
            (f64::MAX, f64::MIN, f64::MAX, f64::MIN),
            |(a, b, c, d), &(x, y)| (a.min(x), b.max(x), c.min(y), d.max(y)),
        );
        let pad = |lo: &mut f64, hi: &mut f64| {
            let span = (*hi - *lo).max(1e-9);
            *lo -= 0.04 * span;
            *hi += 0.04 * span;
        };
        pad(&mut x0, &mut x1);
        pad(&mut y0, &mut y1);
        let mut chart = ChartBuilder::on(area)
            .caption(&panel.title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| e.to_string())?;
        let (xl, yl) = (panel.x_log, panel.y_log);
        chart
            .configure_mesh()
            .x_desc(&panel.x_label)
            .y_desc(&panel.y_label)
            .x_label_formatter(&|v| label(*v, xl))
            .y_label_formatter(&|v| label(*v, yl))
            .draw()
            .map_err(|e| e.to_string())?;
        for (s, p) in panel.series.iter().zip(&pts) {
            let color = PALETTE[s.color % PALETTE.len()];
            if s.line {
                chart
                    .draw_series(LineSeries::new(p.clone(), color.stroke_width(2)))
                    .map_err(|e| e.to_string())?
                    .label(&s.label)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color));
            }
            if s.markers {
                let series = chart
                    .draw_series(p.iter().map(|&q| Circle::new(q, 4, color.filled())))
                    .map_err(|e| e.to_string())?;
                if !s.line {
                    series
                        .label(&s.label)
                        .legend(move |(x, y)| Circle::new((x + 9, y), 4, color.filled()));
                }
            }
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| e.to_string())?;
    }
    root.present().map_err(|e| e.to_string())
}

/// One cell of a [`Map`]: its fill colour and up to a few lines of text.
pub struct MapCell {
    /// Fill colour (r, g, b).
    pub color: (u8, u8, u8),
    /// Text lines, centred in the cell.
    pub lines: Vec<String>,
}

/// A categorical map: a grid of coloured cells with row and column labels and a legend.
pub struct Map {
    /// Title above the grid.
    pub title: String,
    /// One label per row (left of the grid).
    pub row_labels: Vec<String>,
    /// One label per column (above the grid; `\n` breaks lines).
    pub col_labels: Vec<String>,
    /// Cells, row by row (`cells[row][col]`).
    pub cells: Vec<Vec<MapCell>>,
    /// Legend entries below the grid: (text, colour).
    pub legend: Vec<(String, (u8, u8, u8))>,
    /// Lines of small print under the legend.
    pub notes: Vec<String>,
}

/// Draws `map` into a PNG at `path`, each cell `cell` pixels (width, height), the row
/// labels in a column `label_width` pixels wide.
pub fn draw_map(path: &Path, map: &Map, cell: (u32, u32), label_width: u32) -> Result<(), String> {
    use plotters::style::text_anchor::{HPos, Pos, VPos};
    font();
    let rows = map.row_labels.len() as u32;
    let cols = map.col_labels.len() as u32;
    let header_lines = map
        .col_labels
        .iter()
        .map(|l| l.lines().count())
        .max()
        .unwrap_or(1) as u32;
    let (title_h, line_h) = (40u32, 16u32);
    let header_h = header_lines * line_h + 12;
    let legend_h = 34 + map.notes.len() as u32 * line_h;
    let width = label_width + cols * cell.0 + 20;
    let height = title_h + header_h + rows * cell.1 + legend_h + 10;
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    let e = |e: DrawingAreaErrorKind<_>| e.to_string();
    root.fill(&WHITE).map_err(e)?;
    let text = |size: u32, h: HPos| {
        TextStyle::from(("sans-serif", size).into_font())
            .color(&BLACK)
            .pos(Pos::new(h, VPos::Center))
    };
    root.draw(&Text::new(
        map.title.clone(),
        ((width / 2) as i32, (title_h / 2) as i32),
        text(20, HPos::Center),
    ))
    .map_err(e)?;
    let x0 = label_width as i32;
    let y0 = (title_h + header_h) as i32;
    let (cw, ch) = (cell.0 as i32, cell.1 as i32);
    for (c, label) in map.col_labels.iter().enumerate() {
        let n = label.lines().count() as i32;
        for (k, line) in label.lines().enumerate() {
            let y = y0 - 6 - (n - k as i32) * line_h as i32 + line_h as i32 / 2;
            root.draw(&Text::new(
                line.to_string(),
                (x0 + c as i32 * cw + cw / 2, y),
                text(13, HPos::Center),
            ))
            .map_err(e)?;
        }
    }
    for (r, label) in map.row_labels.iter().enumerate() {
        root.draw(&Text::new(
            label.clone(),
            (x0 - 8, y0 + r as i32 * ch + ch / 2),
            text(14, HPos::Right),
        ))
        .map_err(e)?;
    }
    for (r, row) in map.cells.iter().enumerate() {
        for (c, m) in row.iter().enumerate() {
            let (ax, ay) = (x0 + c as i32 * cw, y0 + r as i32 * ch);
            let (rr, gg, bb) = m.color;
            root.draw(&Rectangle::new(
                [(ax, ay), (ax + cw, ay + ch)],
                RGBColor(rr, gg, bb).filled(),
            ))
            .map_err(e)?;
            root.draw(&Rectangle::new(
                [(ax, ay), (ax + cw, ay + ch)],
                WHITE.stroke_width(2),
            ))
            .map_err(e)?;
            let n = m.lines.len() as i32;
            for (k, line) in m.lines.iter().enumerate() {
                let y = ay + ch / 2 + (2 * k as i32 - (n - 1)) * line_h as i32 / 2;
                root.draw(&Text::new(
                    line.clone(),
                    (ax + cw / 2, y),
                    text(13, HPos::Center),
                ))
                .map_err(e)?;
            }
        }
    }
    // Legend: swatches and names in one line, then the notes.
    let ly = y0 + rows as i32 * ch + 20;
    let mut lx = x0;
    for (name, (rr, gg, bb)) in &map.legend {
        root.draw(&Rectangle::new(
            [(lx, ly - 7), (lx + 14, ly + 7)],
            RGBColor(*rr, *gg, *bb).filled(),
        ))
        .map_err(e)?;
        root.draw(&Text::new(
            name.clone(),
            (lx + 20, ly),
            text(14, HPos::Left),
        ))
        .map_err(e)?;
        lx += 20 + 9 * name.chars().count() as i32 + 24;
    }
    for (k, note) in map.notes.iter().enumerate() {
        root.draw(&Text::new(
            note.clone(),
            (x0, ly + 20 + k as i32 * line_h as i32),
            text(12, HPos::Left),
        ))
        .map_err(e)?;
    }
    root.present().map_err(|e| e.to_string())
}
