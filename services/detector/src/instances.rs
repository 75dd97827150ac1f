//! From a per-pixel label map to detections: each object's connected
//! regions, near ones merged (an occluder can cut one object in two), small
//! ones dropped, each scored by its mean confidence and scaled up to the
//! frame as a box and the mask inside it.

use crate::DetectedObject;

/// Labels of a downsampled image, row-major: `labels[y·width + x]` is 0 for
/// background or k for the k-th object id of the network; `confidence` is
/// the probability of that label.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelMap {
    pub width: usize,
    pub height: usize,
    pub labels: Vec<u8>,
    pub confidence: Vec<f32>,
}

/// How regions become detections.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InstanceRules {
    /// Regions smaller than this many frame pixels are dropped.
    pub min_pixels: usize,
    /// Regions of one object whose boxes are at most this many frame pixels
    /// apart are one instance.
    pub merge_gap_px: usize,
    /// Instances kept per object, largest first.
    pub max_instances: usize,
    /// Instances whose mean confidence is lower are dropped.
    pub min_score: f32,
}

/// What [`detections`] found and what it left out.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Found {
    pub objects: Vec<DetectedObject>,
    /// Regions below `min_pixels`, instances below `min_score` or beyond
    /// `max_instances`.
    pub dropped: usize,
}

/// One connected region (or a merged group of them) in map cells.
#[derive(Debug, Clone)]
struct Region {
    class: u8,
    cells: Vec<usize>,
    confidence: f64,
    /// `x0, y0, x1, y1`, inclusive, in map cells.
    bounds: [usize; 4],
}

impl Region {
    fn gap_to(&self, other: &Region) -> usize {
        let gap = |a0: usize, a1: usize, b0: usize, b1: usize| b0.saturating_sub(a1).max(a0.saturating_sub(b1));
        gap(self.bounds[0], self.bounds[2], other.bounds[0], other.bounds[2]).max(gap(
            self.bounds[1],
            self.bounds[3],
            other.bounds[1],
            other.bounds[3],
        ))
    }

    fn absorb(&mut self, other: Region) {
        self.cells.extend(other.cells);
        self.confidence += other.confidence;
        self.bounds = [
            self.bounds[0].min(other.bounds[0]),
            self.bounds[1].min(other.bounds[1]),
            self.bounds[2].max(other.bounds[2]),
            self.bounds[3].max(other.bounds[3]),
        ];
    }
}

/// 4-connected regions of each non-zero label.
fn regions(map: &LabelMap) -> Vec<Region> {
    let (w, h) = (map.width, map.height);
    let mut seen = vec![false; w * h];
    let mut found = Vec::new();
    let mut stack = Vec::new();
    for start in 0..w * h {
        let class = map.labels[start];
        if class == 0 || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut region = Region { class, cells: Vec::new(), confidence: 0.0, bounds: [w, h, 0, 0] };
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            region.cells.push(i);
            region.confidence += f64::from(map.confidence[i]);
            region.bounds =
                [region.bounds[0].min(x), region.bounds[1].min(y), region.bounds[2].max(x), region.bounds[3].max(y)];
            for n in crate::grid_neighbours(i, w, h).into_iter().flatten() {
                if !seen[n] && map.labels[n] == class {
                    seen[n] = true;
                    stack.push(n);
                }
            }
        }
        found.push(region);
    }
    found
}

/// The detections of `map` in a `frame_width × frame_height` frame;
/// `object_ids[k - 1]` is the object of label k.
pub fn detections(
    map: &LabelMap,
    object_ids: &[u32],
    frame_width: usize,
    frame_height: usize,
    rules: &InstanceRules,
) -> Found {
    let (sx, sy) = (frame_width as f64 / map.width as f64, frame_height as f64 / map.height as f64);
    let min_cells = (rules.min_pixels as f64 / (sx * sy)).ceil() as usize;
    let gap_cells = (rules.merge_gap_px as f64 / sx.max(sy)).round() as usize;
    let mut all = regions(map);
    let mut dropped = 0;
    all.retain(|r| {
        let keep = r.cells.len() >= min_cells.max(1);
        dropped += usize::from(!keep);
        keep
    });
    // Largest first, so each object's main region seeds its first instance.
    all.sort_by(|a, b| b.cells.len().cmp(&a.cells.len()).then(a.cells[0].cmp(&b.cells[0])));
    let mut instances: Vec<Region> = Vec::new();
    for region in all {
        match instances.iter_mut().find(|i| i.class == region.class && i.gap_to(&region) <= gap_cells) {
            Some(instance) => instance.absorb(region),
            None => instances.push(region),
        }
    }
    let mut objects = Vec::new();
    let mut per_class = vec![0usize; 256];
    for instance in instances {
        let score = (instance.confidence / instance.cells.len() as f64) as f32;
        let Some(&obj_id) = object_ids.get(usize::from(instance.class) - 1) else {
            dropped += 1;
            continue;
        };
        let count = &mut per_class[usize::from(instance.class)];
        if score < rules.min_score || *count >= rules.max_instances {
            dropped += 1;
            continue;
        }
        let object = to_frame(map, &instance, obj_id, *count as u32, score, frame_width, frame_height);
        // A frame smaller than the map leaves some cells without a pixel.
        if !object.mask.contains(&true) {
            dropped += 1;
            continue;
        }
        objects.push(object);
        *count += 1;
    }
    Found { objects, dropped }
}

/// Scales a region up to the frame: the frame pixels whose nearest map cell
/// (the one whose block holds them) is in the region.
fn to_frame(
    map: &LabelMap,
    region: &Region,
    obj_id: u32,
    instance: u32,
    score: f32,
    fw: usize,
    fh: usize,
) -> DetectedObject {
    let (w, h) = (map.width, map.height);
    let mut inside = vec![false; w * h];
    for &c in &region.cells {
        inside[c] = true;
    }
    let [cx0, cy0, cx1, cy1] = region.bounds;
    // Frame pixels u with cell floor(u·w/fw) in [cx0, cx1].
    let first = |cell: usize, cells: usize, pixels: usize| (cell * pixels).div_ceil(cells);
    let (x0, x1) = (first(cx0, w, fw), first(cx1 + 1, w, fw).min(fw));
    let (y0, y1) = (first(cy0, h, fh), first(cy1 + 1, h, fh).min(fh));
    let (bw, bh) = (x1 - x0, y1 - y0);
    let mut mask = Vec::with_capacity(bw * bh);
    for v in y0..y1 {
        let cy = v * h / fh;
        for u in x0..x1 {
            mask.push(inside[cy * w + u * w / fw]);
        }
    }
    DetectedObject { obj_id, instance, score, bbox: [x0 as u32, y0 as u32, bw as u32, bh as u32], mask }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const RULES: InstanceRules = InstanceRules { min_pixels: 16, merge_gap_px: 8, max_instances: 1, min_score: 0.3 };

    fn map_with(width: usize, height: usize, boxes: &[(u8, [usize; 4])]) -> LabelMap {
        let mut labels = vec![0; width * height];
        for &(class, [x0, y0, x1, y1]) in boxes {
            for y in y0..=y1 {
                for x in x0..=x1 {
                    labels[y * width + x] = class;
                }
            }
        }
        LabelMap { width, height, confidence: vec![0.9; width * height], labels }
    }

    #[test]
    fn a_square_region_scales_to_its_frame_box_and_mask() {
        // Cells 2..=3 of a 10-wide map over a 40-wide frame: pixels 8..16.
        let map = map_with(10, 10, &[(1, [2, 2, 3, 3])]);
        let found = detections(&map, &[7], 40, 40, &RULES);
        assert_eq!(found.dropped, 0);
        let [object] = found.objects.as_slice() else { panic!("{found:?}") };
        assert_eq!((object.obj_id, object.instance, object.bbox), (7, 0, [8, 8, 8, 8]));
        assert!(object.mask.iter().all(|&m| m));
        assert!((object.score - 0.9).abs() < 1e-6);
    }

    #[test]
    fn near_regions_of_one_object_merge_and_far_ones_are_further_instances() {
        // Two pieces 1 cell (4 px) apart merge; a third 5 cells away does not.
        let map = map_with(20, 10, &[(1, [0, 0, 2, 2]), (1, [4, 0, 5, 2]), (1, [11, 0, 12, 1])]);
        let one = detections(&map, &[3], 80, 40, &RULES);
        assert_eq!((one.objects.len(), one.dropped), (1, 1));
        assert_eq!(one.objects[0].bbox, [0, 0, 24, 12]);
        // The gap between the merged pieces is not in the mask.
        assert!(!one.objects[0].mask[12]);
        let two = detections(&map, &[3], 80, 40, &InstanceRules { max_instances: 2, ..RULES });
        assert_eq!(two.objects.iter().map(|o| o.instance).collect::<Vec<_>>(), [0, 1]);
    }

    #[test]
    fn small_and_unsure_regions_are_dropped_and_counted() {
        let mut map = map_with(10, 10, &[(1, [0, 0, 0, 0]), (2, [5, 5, 8, 8])]);
        map.confidence.iter_mut().for_each(|c| *c = 0.2);
        let found = detections(&map, &[1, 2], 40, 40, &RULES);
        assert_eq!((found.objects.len(), found.dropped), (0, 2));
    }

    proptest! {
        /// Every mask pixel lies in its box, inside the frame, and maps back
        /// to a cell of the object's label; every labelled cell big enough
        /// to keep is covered.
        #[test]
        fn masks_are_the_labelled_cells_scaled_up(
            cells in proptest::collection::vec(0u8..3, 8 * 6),
            (fw, fh) in (1usize..64, 1usize..48),
        ) {
            let map = LabelMap { width: 8, height: 6, confidence: vec![1.0; 48], labels: cells };
            let rules = InstanceRules { min_pixels: 1, merge_gap_px: 0, max_instances: 100, min_score: 0.0 };
            let found = detections(&map, &[1, 2], fw, fh, &rules);
            let mut covered = [false; 48];
            for o in &found.objects {
                let [x, y, w, h] = o.bbox.map(|v| v as usize);
                prop_assert!(x + w <= fw && y + h <= fh && o.mask.len() == w * h);
                for (i, &m) in o.mask.iter().enumerate() {
                    let (u, v) = (x + i % w, y + i / w);
                    let cell = (v * 6 / fh) * 8 + u * 8 / fw;
                    if m {
                        prop_assert_eq!(u32::from(map.labels[cell]), o.obj_id);
                        covered[cell] = true;
                    }
                }
            }
            for o in &found.objects {
                prop_assert!(o.bbox[2] > 0 && o.bbox[3] > 0 && o.mask.contains(&true), "an empty detection: {:?}", o);
            }
            // A cell owns at least one frame pixel when the frame is at
            // least as large as the map.
            if fw >= 8 && fh >= 6 {
                for (cell, &label) in map.labels.iter().enumerate() {
                    prop_assert!(label == 0 || covered[cell], "cell {} of label {} not covered", cell, label);
                }
            }
        }
    }
}
