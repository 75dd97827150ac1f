//! Ingest → inference: one object's crop, token mask and point cloud.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, bounded, header_accessors, limits, sections};
use crate::{ContractError, Header};

/// Pinhole intrinsics of the full camera image (pixels): `u = fx·x/z + cx`,
/// `v = fy·y/z + cy`, pixel centres at integer coordinates, `(0, 0)` the
/// centre of the top-left pixel (OpenCV and BOP convention).
///
/// | offset | size | field  | type |
/// |-------:|-----:|--------|------|
/// | 0      | 4    | fx     | f32  |
/// | 4      | 4    | fy     | f32  |
/// | 8      | 4    | cx     | f32  |
/// | 12     | 4    | cy     | f32  |
/// | 16     | 4    | width  | u32  |
/// | 20     | 4    | height | u32  |
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/CameraIntrinsics/v1")]
pub struct CameraIntrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

/// User header of an Observation (160 bytes, alignment 8).
///
/// | offset | size | field             | type     | meaning |
/// |-------:|-----:|-------------------|----------|---------|
/// | 0      | 80   | header            | [`Header`] | frame, object, flags, stamps |
/// | 80     | 24   | intrinsics        | [`CameraIntrinsics`] | of the full image |
/// | 104    | 12   | centroid          | [f32; 3] | camera frame, metres: the mean that was subtracted from the points |
/// | 116    | 4    | point_scale       | f32      | points are `(x_cam − centroid) / point_scale`; 1 = metres |
/// | 120    | 16   | crop              | [f32; 4] | `x_min, y_min, x_max, y_max` of the square crop, full-image pixels |
/// | 136    | 4    | image_size        | u32      | S: the crop is resized to S×S |
/// | 140    | 4    | patch_grid        | u32      | P: the image encoder sees P×P patch tokens (S divisible by P) |
/// | 144    | 4    | point_count       | u32      | N: points in the payload |
/// | 148    | 4    | valid_point_count | u32      | distinct observed points before resampling to N |
/// | 152    | 4    | depth_grid        | u32      | G: the depth and mask sections are G×G; 0 = no such sections |
/// | 156    | 4    | depth_span        | f32      | the depth grid's square: the crop scaled by this about its centre |
///
/// Payload (`f32`): `image` 3·S·S (CHW, RGB, normalised with the model's mean
/// and std) ‖ `token_mask` P·P (1 = patch overlaps the object mask, 0 = not;
/// row-major over patch rows) ‖ `points` N·3 (x, y, z interleaved) ‖
/// `depth` G·G ‖ `mask` G·G.
///
/// `depth` and `mask` sample one square on a G×G grid, row-major over grid
/// rows: the crop scaled by `depth_span` about its centre (wider than the
/// crop, so that a pose putting the object beyond the mask is seen there).
/// With that square's corner `(x₀, y₀)` and side `d`, cell `(j, i)` holds
/// the full image's pixel nearest to `(x₀ + (j + ½)·d/G, y₀ + (i + ½)·d/G)`.
/// `depth` is its camera
/// z in metres, everything the camera saw there and not only the object (0 =
/// no depth, or outside the image); `mask` is 1 where the pixel is the
/// object's, 0 elsewhere. They let a consumer test a pose against free space:
/// the camera seeing beyond where the posed object would be.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/Observation/v2")]
pub struct ObservationHeader {
    pub header: Header,
    pub intrinsics: CameraIntrinsics,
    pub centroid: [f32; 3],
    pub point_scale: f32,
    pub crop: [f32; 4],
    pub image_size: u32,
    pub patch_grid: u32,
    pub point_count: u32,
    pub valid_point_count: u32,
    pub depth_grid: u32,
    pub depth_span: f32,
}

/// The sections of an Observation payload.
#[derive(Debug, Clone, Copy)]
pub struct ObservationView<'a> {
    pub image: &'a [f32],
    pub token_mask: &'a [f32],
    pub points: &'a [f32],
    /// Empty when `depth_grid` is 0.
    pub depth: &'a [f32],
    pub mask: &'a [f32],
}

impl ObservationHeader {
    fn section_lengths(&self) -> Result<[usize; 5], ContractError> {
        let s = bounded(Self::NAME, "image_size", self.image_size, 1, limits::MAX_IMAGE_SIZE, "1..=1024 pixels")?;
        let p = bounded(
            Self::NAME,
            "patch_grid",
            self.patch_grid,
            1,
            self.image_size,
            "1..=image_size and a divisor of image_size",
        )?;
        if s % p != 0 {
            return Err(ContractError::FieldOutOfRange {
                message: Self::NAME,
                field: "patch_grid",
                value: u64::from(self.patch_grid),
                expected: "a divisor of image_size",
            });
        }
        let n = bounded(Self::NAME, "point_count", self.point_count, 1, limits::MAX_POINTS, "1..=65536")?;
        bounded(Self::NAME, "valid_point_count", self.valid_point_count, 0, self.point_count, "0..=point_count")?;
        let g = bounded(Self::NAME, "depth_grid", self.depth_grid, 0, limits::MAX_DEPTH_GRID, "0..=256 cells")?;
        Ok([3 * s * s, p * p, 3 * n, g * g, g * g])
    }

    /// Splits a payload that [`MessageHeader::check_payload`] accepts.
    pub fn view<'a>(&self, payload: &'a [f32]) -> Result<ObservationView<'a>, ContractError> {
        self.check_payload(payload)?;
        let [image, token_mask, points, depth, mask] = sections(payload, self.section_lengths()?);
        Ok(ObservationView { image, token_mask, points, depth, mask })
    }
}

impl MessageHeader for ObservationHeader {
    const NAME: &'static str = "Observation";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        Ok(self.section_lengths()?.iter().sum())
    }
}
