//! The demo's pictures (see `poseflow-figures`): model outlines over the
//! RGB image, Mollweide plots of rotation samples (as in implicit-pdf) and
//! the tracking error per image.

use std::f64::consts::{PI, SQRT_2, TAU};
use std::path::Path;

use image::{Rgb, RgbImage};
use nalgebra::{Rotation3, Vector3};
use poseflow_figures::plotters::prelude::*;
use poseflow_figures::plotters::style::text_anchor::{HPos, Pos, VPos};
use poseflow_figures::{
    Area, DrawError, FigureError, MARGIN, TITLE_HEIGHT, colour_bar, hue, image_panel, image_panel_size, legend,
    legend_line, line_key, render, text, titled,
};
use poseflow_geometry::Pose;
use poseflow_scene::bop::Raster;
use poseflow_scene::{Camera, Placed, RenderModel, silhouettes};

const SELECTED: RGBColor = RGBColor(40, 230, 60);
const HYPOTHESIS: RGBColor = RGBColor(255, 170, 0);

/// One object drawn on the overlay.
pub struct Outlined<'a> {
    pub obj_id: u32,
    pub model: &'a RenderModel,
    pub selected: Pose,
    pub hypotheses: Vec<Pose>,
}

/// Pixels inside `mask` with a 4-neighbour outside it.
fn boundary(mask: &[bool], width: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
    let height = mask.len() / width;
    (0..mask.len()).filter(move |&i| mask[i]).filter_map(move |i| {
        let (x, y) = (i % width, i / width);
        let outside = |dx: i64, dy: i64| {
            let (nx, ny) = (x as i64 + dx, y as i64 + dy);
            nx < 0 || ny < 0 || nx >= width as i64 || ny >= height as i64 || !mask[ny as usize * width + nx as usize]
        };
        (outside(1, 0) || outside(-1, 0) || outside(0, 1) || outside(0, -1)).then_some((x, y))
    })
}

/// The RGB image (dimmed) with each object's outline under a handful of
/// hypotheses (orange) and under the selected pose (green, thicker), its id
/// beside the selected outline, in pixel axes (origin top left, as the
/// camera intrinsics count).
pub fn overlay(
    rgb: &Raster<[u8; 3]>,
    camera: &Camera,
    objects: &[Outlined<'_>],
    path: &Path,
) -> Result<(), FigureError> {
    let (width, height) = (rgb.width, rgb.height);
    let mut image = RgbImage::from_fn(width, height, |x, y| {
        Rgb(rgb.pixels[(y * width + x) as usize].map(|c| (u16::from(c) * 3 / 4) as u8))
    });
    let mut labels = Vec::new();
    for object in objects {
        let drawn: Vec<(Pose, RGBColor, i64)> = object
            .hypotheses
            .iter()
            .map(|p| (*p, HYPOTHESIS, 0))
            .chain(std::iter::once((object.selected, SELECTED, 1)))
            .collect();
        let placed: Vec<Placed<'_>> = drawn.iter().map(|(pose, _, _)| Placed { model: object.model, pose }).collect();
        for (mask, (_, colour, thickness)) in silhouettes(camera, &placed).iter().zip(&drawn) {
            let mut top_left: Option<(usize, usize)> = None;
            for (x, y) in boundary(mask, width as usize) {
                top_left = Some(top_left.map_or((x, y), |(tx, ty)| (tx.min(x), ty.min(y))));
                for dy in -thickness..=*thickness {
                    for dx in -thickness..=*thickness {
                        let (px, py) = (x as i64 + dx, y as i64 + dy);
                        if px >= 0 && py >= 0 && px < i64::from(width) && py < i64::from(height) {
                            image.put_pixel(px as u32, py as u32, Rgb([colour.0, colour.1, colour.2]));
                        }
                    }
                }
            }
            if *thickness == 1
                && let Some(corner) = top_left
            {
                labels.push((object.obj_id, corner));
            }
        }
    }
    render(path, "overlay", image_panel_size(width, height), |root| {
        let mut chart = image_panel(root, &image, "Pose outlines on the input image")?;
        let pixels = chart.plotting_area().strip_coord_spec();
        for (obj_id, (x, y)) in &labels {
            let above = (*y as i32 - 18).max(0);
            pixels.draw_text(&format!("object {obj_id}"), &text(14).color(&SELECTED), (*x as i32, above))?;
        }
        legend_line(&mut chart, "selected pose", SELECTED, 3)?;
        legend_line(&mut chart, "hypotheses", HYPOTHESIS, 1)?;
        legend(&mut chart, SeriesLabelPosition::UpperRight)
    })
}

/// Longitude and latitude of the first column of `r` (implicit-pdf's
/// convention: longitude = atan2(x, −y), latitude = asin(z)) and the tilt
/// about that axis in [0, 2π).
pub fn sphere_coordinates(r: &Rotation3<f64>) -> (f64, f64, f64) {
    let axis: Vector3<f64> = r.matrix().column(0).into_owned();
    let longitude = axis.x.atan2(-axis.y);
    let latitude = axis.z.clamp(-1.0, 1.0).asin();
    // The tilt: the second column's angle in a frame perpendicular to the
    // axis that depends on the axis only.
    let reference = if axis.z.abs() < 0.99 { Vector3::z() } else { Vector3::y() };
    let u = reference.cross(&axis).normalize();
    let v = axis.cross(&u);
    let second: Vector3<f64> = r.matrix().column(1).into_owned();
    let tilt = second.dot(&v).atan2(second.dot(&u)).rem_euclid(TAU);
    (longitude, latitude, tilt)
}

/// Mollweide projection to `[-2√2, 2√2] × [-√2, √2]`.
pub fn mollweide(longitude: f64, latitude: f64) -> (f64, f64) {
    // Solve 2θ + sin 2θ = π sin φ by Newton's method (safe near the poles).
    let target = PI * latitude.sin();
    let mut theta = latitude;
    for _ in 0..20 {
        let f = 2.0 * theta + (2.0 * theta).sin() - target;
        let derivative = 2.0 + 2.0 * (2.0 * theta).cos();
        if derivative.abs() < 1e-12 {
            break;
        }
        theta -= f / derivative;
    }
    (2.0 * SQRT_2 / PI * longitude * theta.cos(), SQRT_2 * theta.sin())
}

/// 181 points of a curve parametrised over [0, 1].
fn curve(point: impl Fn(f64) -> (f64, f64)) -> impl Iterator<Item = (f64, f64)> {
    (0..=180).map(move |i| point(f64::from(i) / 180.0))
}

/// The rotation samples of one object and its ground truth.
pub struct SamplePanel<'a> {
    pub obj_id: u32,
    pub samples: &'a [Pose],
    pub truth: Pose,
}

const PANEL_SIZE: (u32, u32) = (800, 340);
const COLOUR_BAR_WIDTH: u32 = 130;

/// One panel per object, stacked: the samples' rotations as dots coloured
/// by tilt, the ground truth as a ring of its tilt's colour, a graticule
/// every 30° of latitude and 60° of longitude, and the tilt's colour bar.
pub fn mollweide_panels(panels: &[SamplePanel<'_>], path: &Path) -> Result<(), FigureError> {
    let size = (PANEL_SIZE.0, TITLE_HEIGHT + PANEL_SIZE.1 * panels.len().max(1) as u32);
    render(path, "Mollweide plot", size, |root| {
        let (title, rest) = titled(root, "Rotation samples: direction of their x axis (Mollweide)")?;
        // One legend for every panel, at the title's right.
        let legend_x = PANEL_SIZE.0 as i32 - 335;
        title.draw(&Circle::new((legend_x, 19), 3, hue(0.0).filled()))?;
        title.draw_text("sample (colour: tilt)", &text(12), (legend_x + 8, 12))?;
        title.draw(&Circle::new((legend_x + 150, 19), 9, BLACK.stroke_width(2)))?;
        title.draw_text("ground truth (colour: tilt)", &text(12), (legend_x + 164, 12))?;
        for (panel, area) in panels.iter().zip(rest.split_evenly((panels.len().max(1), 1))) {
            sample_panel(panel, &area)?;
        }
        Ok(())
    })
}

fn sample_panel(panel: &SamplePanel<'_>, area: &Area<'_>) -> Result<(), DrawError> {
    let (map, bar) = area.split_horizontally(PANEL_SIZE.0 - COLOUR_BAR_WIDTH);
    let (half_width, half_height) = (2.0 * SQRT_2, SQRT_2);
    let mut chart = ChartBuilder::on(&map)
        .caption(format!("object {}: {} samples", panel.obj_id, panel.samples.len()), text(15))
        .margin(MARGIN)
        .x_label_area_size(24)
        .y_label_area_size(24)
        // Room left of the map for the latitude labels.
        .build_cartesian_2d(-half_width - 0.5..half_width + 0.05, -half_height - 0.05..half_height + 0.05)?;
    // The projection's axes are curved: the graticule carries the degrees.
    chart
        .configure_mesh()
        .disable_mesh()
        .x_labels(0)
        .y_labels(0)
        .x_desc("longitude (°, labels on the equator)")
        .y_desc("latitude (°)")
        .axis_desc_style(text(13))
        .draw()?;
    let right_aligned = text(12).pos(Pos::new(HPos::Right, VPos::Center));
    chart.draw_series([-60.0f64, -30.0, 0.0, 30.0, 60.0].map(|degrees| {
        let (x, y) = mollweide(-PI, degrees.to_radians());
        Text::new(format!("{degrees:.0}°"), (x - 0.06, y), right_aligned.clone())
    }))?;
    let below = text(12).pos(Pos::new(HPos::Center, VPos::Top));
    chart.draw_series([-120.0f64, -60.0, 0.0, 60.0, 120.0].map(|degrees| {
        let (x, y) = mollweide(degrees.to_radians(), 0.0);
        Text::new(format!("{degrees:.0}°"), (x, y - 0.04), below.clone())
    }))?;
    let grey = RGBColor(205, 205, 205);
    for degrees in [-60.0f64, -30.0, 0.0, 30.0, 60.0] {
        chart.draw_series(LineSeries::new(curve(|t| mollweide((t - 0.5) * TAU, degrees.to_radians())), grey))?;
    }
    for degrees in [-120.0f64, -60.0, 0.0, 60.0, 120.0] {
        chart.draw_series(LineSeries::new(curve(|t| mollweide(degrees.to_radians(), (t - 0.5) * PI)), grey))?;
    }
    for edge in [-PI, PI] {
        chart.draw_series(LineSeries::new(curve(|t| mollweide(edge, (t - 0.5) * PI)), RGBColor(90, 90, 90)))?;
    }
    chart.draw_series(panel.samples.iter().map(|pose| {
        let (longitude, latitude, tilt) = sphere_coordinates(&pose.rotation);
        Circle::new(mollweide(longitude, latitude), 3, hue(tilt / TAU).filled())
    }))?;
    let (longitude, latitude, tilt) = sphere_coordinates(&panel.truth.rotation);
    let truth = mollweide(longitude, latitude);
    chart.draw_series([
        Circle::new(truth, 11, BLACK.stroke_width(1)),
        Circle::new(truth, 9, hue(tilt / TAU).stroke_width(3)),
    ])?;
    let degrees = |d: f64| format!("{d:.0}°");
    colour_bar(&bar, "tilt about it", (0.0, 360.0), &[0.0, 90.0, 180.0, 270.0, 360.0], |d| hue(d / 360.0), degrees)
}

/// Top of the error plot's y axis, degrees: larger errors are drawn at the top.
const PLOT_MAX_DEG: f64 = 20.0;

/// The rotation error of one object per image, `(image, degrees)` in image order.
pub struct ErrorSeries {
    pub obj_id: u32,
    pub points: Vec<(u32, f64)>,
    /// Images whose estimate was flagged `LOST`: crosses at the top.
    pub lost: Vec<u32>,
}

/// Rotation error per image, one line per object, x from image 0 to
/// `frames − 1`, y from 0 to 20° (larger errors clipped to the top), lines
/// at the 5° and 10° thresholds; images flagged `LOST` as crosses along the
/// top, one row per object.
pub fn error_plot(series: &[ErrorSeries], frames: u32, path: &Path) -> Result<(), FigureError> {
    let last = frames.max(2) - 1;
    render(path, "tracking error plot", (900, 380), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption("Rotation error of the selected pose per image of the video", text(17))
            .margin(MARGIN)
            .x_label_area_size(42)
            .y_label_area_size(56)
            .build_cartesian_2d(0..last, 0.0..PLOT_MAX_DEG)?;
        chart
            .configure_mesh()
            .x_desc("image (video frame)")
            .y_desc(format!("rotation error (°, clipped at {PLOT_MAX_DEG:.0}°)"))
            .y_label_formatter(&|degrees: &f64| format!("{degrees:.0}"))
            .light_line_style(RGBColor(240, 240, 240))
            .label_style(text(13))
            .axis_desc_style(text(13))
            .draw()?;
        for (degrees, colour) in [(5.0, RGBColor(120, 120, 120)), (10.0, RGBColor(170, 170, 170))] {
            chart
                .draw_series(LineSeries::new([(0, degrees), (last, degrees)], colour.stroke_width(2)))?
                .label(format!("{degrees:.0}° threshold"))
                .legend(line_key(colour, 2));
        }
        for (k, object) in series.iter().enumerate() {
            let colour = hue(k as f64 / series.len() as f64);
            let clipped = || object.points.iter().map(|&(im_id, degrees)| (im_id, degrees.clamp(0.0, PLOT_MAX_DEG)));
            chart
                .draw_series(LineSeries::new(clipped(), colour.stroke_width(2)))?
                .label(format!("object {}", object.obj_id))
                .legend(line_key(colour, 2));
            chart.draw_series(clipped().map(|point| Circle::new(point, 2, colour.filled())))?;
            let top = PLOT_MAX_DEG * (0.97 - 0.04 * k as f64);
            chart.draw_series(object.lost.iter().map(|&im_id| Cross::new((im_id, top), 4, colour.stroke_width(2))))?;
        }
        legend(&mut chart, SeriesLabelPosition::UpperRight)
    })
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;
    use poseflow_scene::primitives::ClutterShape;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("poseflow-pictures-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    /// Pixels of `image` inside the rectangle that are close to `colour`.
    fn count(image: &RgbImage, (x0, y0, x1, y1): (u32, u32, u32, u32), colour: [u8; 3]) -> usize {
        let near = |p: &Rgb<u8>| p.0.iter().zip(colour).all(|(a, b)| a.abs_diff(b) < 40);
        (y0..y1.min(image.height()))
            .flat_map(|y| (x0..x1.min(image.width())).map(move |x| (x, y)))
            .filter(|&(x, y)| near(image.get_pixel(x, y)))
            .count()
    }

    /// Dark pixels: text and axes (anti-aliased text is mostly grey).
    fn ink(image: &RgbImage, rect: (u32, u32, u32, u32)) -> usize {
        count(image, rect, [40, 40, 40]) + count(image, rect, [110, 110, 110])
    }

    #[test]
    fn the_error_plot_has_a_title_labelled_axes_and_a_legend() {
        let path = scratch("tracking.png");
        let low = |obj_id, degrees| ErrorSeries {
            obj_id,
            points: (0..30).map(|i| (i, degrees)).collect(),
            lost: vec![10, 11],
        };
        error_plot(&[low(1, 1.0), low(5, 2.0)], 30, &path).unwrap();
        let image = image::open(&path).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (900, 380));
        assert!(ink(&image, (0, 0, 900, 32)) > 200, "title");
        assert!(ink(&image, (0, 40, 60, 330)) > 200, "y axis labels and description");
        assert!(ink(&image, (60, 340, 900, 380)) > 200, "x axis labels and description");
        // Both series run at the bottom: the first's colour near the top
        // right is its legend entry.
        let first = hue(0.0);
        assert!(count(&image, (600, 30, 900, 200), [first.0, first.1, first.2]) > 10, "legend");
    }

    #[test]
    fn the_mollweide_plot_has_a_title_graticule_labels_and_a_colour_bar() {
        let path = scratch("mollweide.png");
        let samples: Vec<Pose> = (0..20)
            .map(|k| Pose::new(Rotation3::from_axis_angle(&Vector3::z_axis(), f64::from(k) * 0.3), Vector3::zeros()))
            .collect();
        let panel = |obj_id| SamplePanel { obj_id, samples: &samples, truth: Pose::identity() };
        mollweide_panels(&[panel(1), panel(8)], &path).unwrap();
        let image = image::open(&path).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (PANEL_SIZE.0, TITLE_HEIGHT + 2 * PANEL_SIZE.1));
        assert!(ink(&image, (0, 0, PANEL_SIZE.0, TITLE_HEIGHT)) > 200, "title");
        for panel in 0..2 {
            let top = TITLE_HEIGHT + panel * PANEL_SIZE.1;
            assert!(ink(&image, (0, top, PANEL_SIZE.0, top + 30)) > 100, "panel {panel} caption");
            // The tilt colour bar: every hue down its height.
            let bar = (PANEL_SIZE.0 - COLOUR_BAR_WIDTH, top, PANEL_SIZE.0, top + PANEL_SIZE.1);
            for fraction in [0.0, 1.0 / 3.0, 2.0 / 3.0] {
                let c = hue(fraction);
                assert!(count(&image, bar, [c.0, c.1, c.2]) > 50, "panel {panel} colour bar at {fraction}");
            }
        }
    }

    #[test]
    fn the_overlay_outlines_poses_and_names_them_in_a_legend() {
        let path = scratch("overlay.png");
        let cube = ClutterShape::Box { half_extents: Vector3::new(0.03, 0.03, 0.03) }.mesh([200, 50, 50]);
        let model = RenderModel::new(cube).unwrap();
        let camera = Camera { fx: 300.0, fy: 300.0, cx: 160.0, cy: 120.0, width: 320, height: 240 };
        let rgb = Raster { width: 320, height: 240, pixels: vec![[128, 128, 128]; 320 * 240] };
        let at = |x| Pose::new(Rotation3::identity(), Vector3::new(x, 0.0, 0.5));
        let object = Outlined { obj_id: 3, model: &model, selected: at(0.0), hypotheses: vec![at(0.02)] };
        overlay(&rgb, &camera, &[object], &path).unwrap();
        let image = image::open(&path).unwrap().to_rgb8();
        // The panel's axes and title are `poseflow-figures`' (tested there).
        assert_eq!(image.dimensions(), image_panel_size(320, 240));
        let plot = (MARGIN + 56, TITLE_HEIGHT + MARGIN, MARGIN + 56 + 320, TITLE_HEIGHT + MARGIN + 240);
        let green = [SELECTED.0, SELECTED.1, SELECTED.2];
        let orange = [HYPOTHESIS.0, HYPOTHESIS.1, HYPOTHESIS.2];
        // Outlines in the image's middle; legend entries in its top right.
        let middle = (plot.0 + 100, plot.1 + 60, plot.0 + 220, plot.1 + 180);
        assert!(count(&image, middle, green) > 50 && count(&image, middle, orange) > 20, "outlines");
        let corner = (plot.2 - 140, plot.1, plot.2, plot.1 + 60);
        assert!(count(&image, corner, green) > 5 && count(&image, corner, orange) > 5, "legend");
    }

    #[test]
    fn mollweide_maps_the_equator_poles_and_edges_in_closed_form() {
        let (x, y) = mollweide(0.0, 0.0);
        assert!(x.abs() < 1e-12 && y.abs() < 1e-12);
        let (x, y) = mollweide(PI, 0.0);
        assert!((x - 2.0 * SQRT_2).abs() < 1e-9 && y.abs() < 1e-12);
        let (x, y) = mollweide(1.0, PI / 2.0);
        assert!(x.abs() < 1e-6 && (y - SQRT_2).abs() < 1e-9);
    }

    #[test]
    fn sphere_coordinates_follow_the_first_column() {
        let (longitude, latitude, _) = sphere_coordinates(&Rotation3::identity());
        // x axis = (1, 0, 0): atan2(1, -0) = π/2 on the equator.
        assert!((longitude - PI / 2.0).abs() < 1e-12 && latitude.abs() < 1e-12);
        let up = Rotation3::from_axis_angle(&Vector3::y_axis(), -PI / 2.0);
        let (_, latitude, _) = sphere_coordinates(&up);
        assert!((latitude - PI / 2.0).abs() < 1e-9, "{latitude}");
        // Turning about the first column changes only the tilt.
        let turned = Rotation3::from_axis_angle(&Vector3::x_axis(), 1.0);
        let (l0, b0, t0) = sphere_coordinates(&Rotation3::identity());
        let (l1, b1, t1) = sphere_coordinates(&turned);
        assert!((l0 - l1).abs() < 1e-12 && (b0 - b1).abs() < 1e-12);
        assert!(((t1 - t0).rem_euclid(TAU) - 1.0).abs() < 1e-9, "{t0} {t1}");
    }
}
