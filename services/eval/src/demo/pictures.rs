//! The demo's pictures: model outlines over the RGB image, and Mollweide
//! plots of rotation samples (as in implicit-pdf).

use std::f64::consts::{PI, SQRT_2, TAU};
use std::path::Path;

use anyhow::Context;
use image::{Rgb, RgbImage};
use nalgebra::{Rotation3, Vector3};
use poseflow_geometry::Pose;
use poseflow_scene::bop::Raster;
use poseflow_scene::{Camera, Placed, RenderModel, silhouettes};

const SELECTED: Rgb<u8> = Rgb([40, 230, 60]);
const HYPOTHESIS: Rgb<u8> = Rgb([255, 170, 0]);

/// One object drawn on the overlay.
pub struct Outlined<'a> {
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

/// The RGB image with each object's outline under a handful of hypotheses
/// (orange) and under the selected pose (green, thicker).
pub fn overlay(rgb: &Raster<[u8; 3]>, camera: &Camera, objects: &[Outlined<'_>], path: &Path) -> anyhow::Result<()> {
    let mut image = RgbImage::from_fn(rgb.width, rgb.height, |x, y| {
        // Dimmed, so the outlines stand out.
        Rgb(rgb.pixels[(y * rgb.width + x) as usize].map(|c| (u16::from(c) * 3 / 4) as u8))
    });
    let width = rgb.width as usize;
    for object in objects {
        let drawn: Vec<(Pose, Rgb<u8>, i64)> = object
            .hypotheses
            .iter()
            .map(|p| (*p, HYPOTHESIS, 0))
            .chain(std::iter::once((object.selected, SELECTED, 1)))
            .collect();
        let placed: Vec<Placed<'_>> = drawn.iter().map(|(pose, _, _)| Placed { model: object.model, pose }).collect();
        for (mask, (_, colour, thickness)) in silhouettes(camera, &placed).iter().zip(&drawn) {
            for (x, y) in boundary(mask, width) {
                for dy in -thickness..=*thickness {
                    for dx in -thickness..=*thickness {
                        let (px, py) = (x as i64 + dx, y as i64 + dy);
                        if px >= 0 && py >= 0 && px < i64::from(rgb.width) && py < i64::from(rgb.height) {
                            image.put_pixel(px as u32, py as u32, *colour);
                        }
                    }
                }
            }
        }
    }
    image.save(path).with_context(|| format!("{}: cannot write the overlay", path.display()))
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

fn hue(fraction: f64) -> Rgb<u8> {
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
    Rgb([r, g, b].map(|c: f64| (c * 230.0) as u8))
}

/// One panel per object, stacked: the samples' rotations as dots coloured
/// by tilt, the ground truth as a ring of its tilt's colour.
pub fn mollweide_panels(panels: &[(Vec<Pose>, Pose)], path: &Path) -> anyhow::Result<()> {
    let (w, h) = (480u32, 240u32);
    let mut image = RgbImage::from_pixel(w, h * panels.len().max(1) as u32, Rgb([255, 255, 255]));
    let to_pixel = |(x, y): (f64, f64), top: u32| -> (i64, i64) {
        let px = (x / (2.0 * SQRT_2) * 0.47 + 0.5) * f64::from(w);
        let py = (0.5 - y / SQRT_2 * 0.45) * f64::from(h) + f64::from(top);
        (px.round() as i64, py.round() as i64)
    };
    let put = |image: &mut RgbImage, (x, y): (i64, i64), colour: Rgb<u8>| {
        if x >= 0 && y >= 0 && x < i64::from(image.width()) && y < i64::from(image.height()) {
            image.put_pixel(x as u32, y as u32, colour);
        }
    };
    for (k, (samples, truth)) in panels.iter().enumerate() {
        let top = k as u32 * h;
        // The map's outline and a graticule every 30 degrees.
        for i in 0..2000 {
            let t = i as f64 / 2000.0;
            for (longitude, latitude) in [(PI, (t - 0.5) * PI), (-PI, (t - 0.5) * PI)] {
                put(&mut image, to_pixel(mollweide(longitude, latitude), top), Rgb([90, 90, 90]));
            }
            for degrees in [-60.0f64, -30.0, 0.0, 30.0, 60.0] {
                let p = to_pixel(mollweide((t - 0.5) * TAU, degrees.to_radians()), top);
                put(&mut image, p, Rgb([215, 215, 215]));
            }
        }
        for pose in samples {
            let (longitude, latitude, tilt) = sphere_coordinates(&pose.rotation);
            let (x, y) = to_pixel(mollweide(longitude, latitude), top);
            for dy in -2..=2 {
                for dx in -2i64..=2 {
                    if dx * dx + dy * dy <= 5 {
                        put(&mut image, (x + dx, y + dy), hue(tilt / TAU));
                    }
                }
            }
        }
        let (longitude, latitude, tilt) = sphere_coordinates(&truth.rotation);
        let (x, y) = to_pixel(mollweide(longitude, latitude), top);
        for i in 0..120 {
            let a = f64::from(i) / 120.0 * TAU;
            for radius in [9.0, 10.0] {
                let p = (x + (radius * a.cos()).round() as i64, y + (radius * a.sin()).round() as i64);
                put(&mut image, p, hue(tilt / TAU));
            }
        }
    }
    image.save(path).with_context(|| format!("{}: cannot write the Mollweide plot", path.display()))
}

/// Top of the error plot's y axis, degrees: larger errors are drawn at the top.
const PLOT_MAX_DEG: f64 = 20.0;

/// Draws a straight segment of one-pixel dots between two points.
fn segment(image: &mut RgbImage, from: (f64, f64), to: (f64, f64), colour: Rgb<u8>) {
    let steps = (to.0 - from.0).abs().max((to.1 - from.1).abs()).ceil().max(1.0) as u32;
    for i in 0..=steps {
        let t = f64::from(i) / f64::from(steps);
        let (x, y) = (from.0 + (to.0 - from.0) * t, from.1 + (to.1 - from.1) * t);
        if x >= 0.0 && y >= 0.0 && x < f64::from(image.width()) && y < f64::from(image.height()) {
            image.put_pixel(x as u32, y as u32, colour);
        }
    }
}

/// Rotation error per image, one polyline per object (`(image, degrees)`
/// points in image order), x from image 0 to `frames`, y from 0 to 20°
/// (clipped), grey lines at 5° and 10°.
pub fn error_plot(series: &[Vec<(u32, f64)>], frames: u32, path: &Path) -> anyhow::Result<()> {
    let (w, h, margin) = (720u32, 240u32, 10.0);
    let mut image = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let x = |im_id: u32| margin + f64::from(im_id) / f64::from(frames.max(2) - 1) * (f64::from(w) - 2.0 * margin);
    let y = |degrees: f64| {
        f64::from(h) - margin - degrees.clamp(0.0, PLOT_MAX_DEG) / PLOT_MAX_DEG * (f64::from(h) - 2.0 * margin)
    };
    for (degrees, grey) in [(0.0, 90), (5.0, 170), (10.0, 170)] {
        segment(&mut image, (x(0), y(degrees)), (x(frames.max(2) - 1), y(degrees)), Rgb([grey; 3]));
    }
    for (k, points) in series.iter().enumerate() {
        let colour = hue(k as f64 / series.len() as f64);
        for pair in points.windows(2) {
            segment(&mut image, (x(pair[0].0), y(pair[0].1)), (x(pair[1].0), y(pair[1].1)), colour);
        }
        if let [(im_id, degrees)] = points.as_slice() {
            segment(&mut image, (x(*im_id), y(*degrees)), (x(*im_id) + 1.0, y(*degrees)), colour);
        }
    }
    image.save(path).with_context(|| format!("{}: cannot write the error plot", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

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
