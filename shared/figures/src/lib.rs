//! The pictures PoseFlow's commands write, drawn with `plotters` in the
//! DejaVu Sans font this crate ships (`fonts/`, so no system font is
//! needed) into memory and written as PNG with `image`. Every picture
//! carries a title, axes with their units and a legend.
//!
//! Images are shown in pixel axes: x to the right, y down from the top left,
//! as camera intrinsics count them, one chart unit per image pixel.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use image::{ExtendedColorType, RgbImage};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordi32;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::{FontStyle, register_font};

pub use plotters;

/// DejaVu Sans (Bitstream Vera licence, `fonts/LICENSE`), the only font.
const FONT: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");
const FONT_FAMILY: &str = "sans-serif";

/// Pixels of a title strip above a picture's charts.
pub const TITLE_HEIGHT: u32 = 36;
/// Pixels around each chart.
pub const MARGIN: u32 = 12;
/// Pixels below and left of an image panel for its axis labels.
const X_LABELS: u32 = 40;
const Y_LABELS: u32 = 56;

/// The drawing area of a picture.
pub type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;
/// An image panel's chart: pixel x to the right, minus the pixel row up.
pub type ImageChart<'a> = ChartContext<'a, BitMapBackend<'a>, Cartesian2d<RangedCoordi32, RangedCoordi32>>;
/// What drawing on a picture can fail with.
pub type DrawError = DrawingAreaErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>;

/// Why a picture could not be drawn or written.
#[derive(Debug, thiserror::Error)]
pub enum FigureError {
    #[error("the shipped font (fonts/DejaVuSans.ttf) is not a readable TrueType font")]
    Font,
    #[error("cannot draw the {picture}")]
    Draw {
        picture: &'static str,
        #[source]
        source: DrawError,
    },
    #[error("{}: cannot write the {picture}", path.display())]
    Write {
        path: PathBuf,
        picture: &'static str,
        #[source]
        source: image::ImageError,
    },
}

/// Text of `size` pixels in the shipped font, black.
pub fn text(size: u32) -> TextStyle<'static> {
    (FONT_FAMILY, size).into_font().color(&BLACK)
}

/// Registers the shipped font with `plotters` once per process.
fn shipped_font() -> Result<(), FigureError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let registered = *REGISTERED.get_or_init(|| register_font(FONT_FAMILY, FontStyle::Normal, FONT).is_ok());
    registered.then_some(()).ok_or(FigureError::Font)
}

/// Draws a picture of `size` pixels (white background) with `draw` and
/// writes it as PNG; `picture` names it in errors.
pub fn render(
    path: &Path,
    picture: &'static str,
    (width, height): (u32, u32),
    draw: impl FnOnce(&Area<'_>) -> Result<(), DrawError>,
) -> Result<(), FigureError> {
    shipped_font()?;
    let mut pixels = vec![255u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (width, height)).into_drawing_area();
        draw(&root).and_then(|()| root.present()).map_err(|source| FigureError::Draw { picture, source })?;
    }
    image::save_buffer(path, &pixels, width, height, ExtendedColorType::Rgb8).map_err(|source| FigureError::Write {
        path: path.to_path_buf(),
        picture,
        source,
    })
}

/// Draws `title` in the strip at the top of `area`; returns the strip (for
/// more in it, such as a legend) and the rest.
pub fn titled<'a>(area: &Area<'a>, title: &str) -> Result<(Area<'a>, Area<'a>), DrawError> {
    let (strip, rest) = area.split_vertically(TITLE_HEIGHT);
    strip.draw_text(title, &text(17), (MARGIN as i32, 10))?;
    Ok((strip, rest))
}

/// Size of an [`image_panel`] of a `width` × `height` image, title included.
pub fn image_panel_size(width: u32, height: u32) -> (u32, u32) {
    (width + Y_LABELS + 2 * MARGIN, height + TITLE_HEIGHT + X_LABELS + 2 * MARGIN)
}

/// `image` under `title` in pixel axes (`x (px)`, `y (px)` from the top
/// left), on an area of [`image_panel_size`]. Returns the chart, for
/// legends and marks in pixel coordinates (x, −row).
pub fn image_panel<'a>(area: &Area<'a>, image: &RgbImage, title: &str) -> Result<ImageChart<'a>, DrawError> {
    let (width, height) = image.dimensions();
    let (_, rest) = titled(area, title)?;
    // The plotting area is exactly the image: one pixel per unit.
    let mut chart = ChartBuilder::on(&rest)
        .margin(MARGIN)
        .x_label_area_size(X_LABELS)
        .y_label_area_size(Y_LABELS)
        .build_cartesian_2d(0..width as i32, -(height as i32)..0)?;
    // Image rows count down from the top; the chart's y counts up, so it
    // runs over minus the row.
    let row = |y: &i32| format!("{}", -y);
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("x (px)")
        .y_desc("y (px)")
        .y_label_formatter(&row)
        .label_style(text(12))
        .axis_desc_style(text(13))
        .draw()?;
    if let Some(picture) = BitMapElement::with_ref((0, 0), (width, height), image.as_raw()) {
        chart.plotting_area().strip_coord_spec().draw(&picture)?;
    }
    Ok(chart)
}

/// Draws the series labels of `chart` as a boxed legend at `position`.
pub fn legend<'a, X, Y>(
    chart: &mut ChartContext<'a, BitMapBackend<'a>, Cartesian2d<X, Y>>,
    position: SeriesLabelPosition,
) -> Result<(), DrawError>
where
    X: plotters::coord::ranged1d::Ranged,
    Y: plotters::coord::ranged1d::Ranged,
{
    chart
        .configure_series_labels()
        .position(position)
        .label_font(text(12))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(120, 120, 120))
        .draw()
}

/// The legend key of a line series: a short line of `colour` and `thickness`
/// (in pixel coordinates of the legend box).
pub fn line_key(colour: RGBColor, thickness: u32) -> impl Fn((i32, i32)) -> PathElement<(i32, i32)> {
    move |(x, y)| PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(thickness))
}

/// A legend entry with no data of its own: a line of `colour` and
/// `thickness` labelled `label`.
pub fn legend_line<'a, X, Y>(
    chart: &mut ChartContext<'a, BitMapBackend<'a>, Cartesian2d<X, Y>>,
    label: &str,
    colour: RGBColor,
    thickness: u32,
) -> Result<(), DrawError>
where
    X: plotters::coord::ranged1d::Ranged,
    Y: plotters::coord::ranged1d::Ranged,
{
    chart
        .draw_series(std::iter::empty::<PathElement<(X::ValueType, Y::ValueType)>>())?
        .label(label)
        .legend(line_key(colour, thickness));
    Ok(())
}

/// A colour of the hue circle (`fraction` of a turn from red), for
/// distinguishing objects and for cyclic quantities.
pub fn hue(fraction: f64) -> RGBColor {
    let h = fraction.rem_euclid(1.0) * 6.0;
    let x = 1.0 - (h % 2.0 - 1.0).abs();
    let (r, g, b) = match h as u32 {
        0 => (1.0, x, 0.0),
        1 => (x, 1.0, 0.0),
        2 => (0.0, 1.0, x),
        3 => (0.0, x, 1.0),
        4 => (x, 0.0, 1.0),
        _ => (1.0, 0.0, x),
    };
    let [r, g, b] = [r, g, b].map(|c: f64| (c * 230.0) as u8);
    RGBColor(r, g, b)
}

/// A vertical colour bar in `area`: `colour(v)` for v from `range.0`
/// (bottom) to `range.1` (top), `ticks` labelled by `label`, under `title`.
pub fn colour_bar(
    area: &Area<'_>,
    title: &str,
    range: (f64, f64),
    ticks: &[f64],
    colour: impl Fn(f64) -> RGBColor,
    label: impl Fn(f64) -> String,
) -> Result<(), DrawError> {
    let (low, high) = range;
    let span = if high > low { high - low } else { 1.0 };
    // The bar spans x in [0, 1]; its labels stand to its right.
    let mut chart = ChartBuilder::on(area)
        .caption(title, text(12))
        .margin(MARGIN)
        .x_label_area_size(38)
        .build_cartesian_2d(0.0..2.6, low..low + span)?;
    const STEPS: u32 = 72;
    chart.draw_series((0..STEPS).map(|k| {
        let from = low + span * f64::from(k) / f64::from(STEPS);
        let to = low + span * f64::from(k + 1) / f64::from(STEPS);
        Rectangle::new([(0.0, from), (1.0, to)], colour((from + to) / 2.0).filled())
    }))?;
    chart.draw_series([Rectangle::new([(0.0, low), (1.0, low + span)], BLACK.stroke_width(1))])?;
    let beside = text(12).pos(Pos::new(HPos::Left, VPos::Center));
    chart.draw_series(ticks.iter().map(|&v| Text::new(label(v), (1.15, v), beside.clone())))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("poseflow-figures-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    fn dark(image: &RgbImage, (x0, y0, x1, y1): (u32, u32, u32, u32)) -> usize {
        (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| (x, y)))
            .filter(|&(x, y)| image.get_pixel(x, y).0.iter().all(|&c| c < 130))
            .count()
    }

    #[test]
    fn an_image_panel_is_the_image_pixel_for_pixel_in_labelled_pixel_axes() {
        let path = scratch("panel.png");
        let image = RgbImage::from_fn(200, 100, |x, y| image::Rgb([x as u8, y as u8, 200]));
        let size = image_panel_size(200, 100);
        render(&path, "panel", size, |root| image_panel(root, &image, "A test image").map(|_| ())).unwrap();
        let drawn = image::open(&path).unwrap().to_rgb8();
        assert_eq!(drawn.dimensions(), size);
        let (left, top) = (MARGIN + Y_LABELS, TITLE_HEIGHT + MARGIN);
        for (x, y) in [(0, 0), (199, 0), (0, 99), (199, 99), (57, 31)] {
            assert_eq!(drawn.get_pixel(left + x, top + y), image.get_pixel(x, y), "pixel ({x}, {y})");
        }
        assert!(dark(&drawn, (0, 0, size.0, TITLE_HEIGHT)) > 100, "title");
        assert!(dark(&drawn, (0, top, left, top + 100)) > 50, "y axis labels");
        assert!(dark(&drawn, (left, top + 100, size.0, size.1)) > 50, "x axis labels");
    }

    #[test]
    fn the_hue_circle_starts_at_red_and_returns_to_it() {
        assert_eq!(hue(0.0), RGBColor(230, 0, 0));
        assert_eq!(hue(1.0), hue(0.0));
        assert_eq!(hue(1.0 / 3.0), RGBColor(0, 230, 0));
        assert_eq!(hue(0.5), RGBColor(0, 230, 230));
    }
}
