//! From a per-pixel label map to detections: each object's connected
//! regions, near ones merged (an occluder can cut one object in two), small
//! ones dropped, each scored by its mean confidence and scaled up to the
//! frame as a box and the mask inside it.
//!
//! A map cell covers a block of frame pixels (4 × 4 for the shipped
//! network), so a mask scaled up cell by cell has block-sized steps, and
//! the blocks along an object's outline hold table or occluder pixels whose
//! depth misleads the pose stages. With `edge_depth_m` set, each frame
//! pixel instead takes a vote of its four nearest cells, weighted bilinearly
//! and by how close each cell's depth is to the pixel's own (joint
//! bilateral upsampling): a pixel goes with the neighbouring cells on its
//! own surface.

use crate::DetectedObject;

/// Labels of a downsampled image, row-major: `labels[y·width + x]` is 0 for
/// background or k for the k-th object id of the network; `confidence` is
/// the probability of that label; `depth` is the depth in metres the
/// labeller saw at each cell (0 where none), or empty when unknown;
/// `instances` says which labelled cells are one object instance (the same
/// non-zero id), or is empty when the labeller does not know (the network:
/// connected regions are found and near ones merged).
#[derive(Debug, Clone, PartialEq)]
pub struct LabelMap {
    pub width: usize,
    pub height: usize,
    pub labels: Vec<u8>,
    pub confidence: Vec<f32>,
    pub depth: Vec<f32>,
    pub instances: Vec<u16>,
}

/// How regions become detections.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InstanceRules {
    /// Regions smaller than this many frame pixels are dropped.
    pub min_pixels: usize,
    /// Regions of one object whose boxes are at most this many frame pixels
    /// apart are one instance.
    pub merge_gap_px: usize,
    /// Instances kept per object, in the order `most_confident_first` sets.
    pub max_instances: usize,
    /// Instances whose mean confidence is lower are dropped.
    pub min_score: f32,
    /// Depth difference (metres) at which a neighbouring cell's vote for a
    /// frame pixel falls to e^-½ of its bilinear weight; 0 scales cells up
    /// as whole blocks.
    pub edge_depth_m: f32,
    /// Instances of an object are kept highest score first (else largest
    /// first).
    pub most_confident_first: bool,
}

/// The frame the detections are for: its size and depth in metres (W·H
/// row-major, 0 where none; empty when unknown).
#[derive(Debug, Clone, Copy)]
pub struct FrameGrid<'a> {
    pub width: usize,
    pub height: usize,
    pub depth: &'a [f32],
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
pub(crate) struct Region {
    pub(crate) class: u8,
    pub(crate) cells: Vec<usize>,
    confidence: f64,
    /// `x0, y0, x1, y1`, inclusive, in map cells.
    pub(crate) bounds: [usize; 4],
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

    /// An empty region of `class` on a map of this size.
    fn empty(class: u8, map: &LabelMap) -> Self {
        Region { class, cells: Vec::new(), confidence: 0.0, bounds: [map.width, map.height, 0, 0] }
    }

    /// Adds cell `i` of `map`.
    fn add(&mut self, i: usize, map: &LabelMap) {
        let (x, y) = (i % map.width, i / map.width);
        self.cells.push(i);
        self.confidence += f64::from(map.confidence[i]);
        self.bounds = [self.bounds[0].min(x), self.bounds[1].min(y), self.bounds[2].max(x), self.bounds[3].max(y)];
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

/// The labeller's own instances: the labelled cells of each instance id.
fn given_instances(map: &LabelMap) -> Vec<Region> {
    let mut by_id: std::collections::BTreeMap<u16, Region> = std::collections::BTreeMap::new();
    for (i, (&class, &id)) in map.labels.iter().zip(&map.instances).enumerate() {
        if class == 0 || id == 0 {
            continue;
        }
        by_id.entry(id).or_insert_with(|| Region::empty(class, map)).add(i, map);
    }
    by_id.into_values().collect()
}

/// 4-connected regions of each non-zero label.
pub(crate) fn regions(map: &LabelMap) -> Vec<Region> {
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
        let mut region = Region::empty(class, map);
        while let Some(i) = stack.pop() {
            region.add(i, map);
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

/// The detections of `map` in `frame`; `object_ids[k - 1]` is the object of
/// label k.
pub fn detections(map: &LabelMap, object_ids: &[u32], frame: &FrameGrid<'_>, rules: &InstanceRules) -> Found {
    let (sx, sy) = (frame.width as f64 / map.width as f64, frame.height as f64 / map.height as f64);
    let min_cells = (rules.min_pixels as f64 / (sx * sy)).ceil() as usize;
    let gap_cells = (rules.merge_gap_px as f64 / sx.max(sy)).round() as usize;
    let given = map.instances.len() == map.labels.len();
    let mut all = if given { given_instances(map) } else { regions(map) };
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
        match instances.iter_mut().find(|i| !given && i.class == region.class && i.gap_to(&region) <= gap_cells) {
            Some(instance) => instance.absorb(region),
            None => instances.push(region),
        }
    }
    if rules.most_confident_first {
        // Stable: equal scores keep the largest first.
        instances
            .sort_by(|a, b| (b.confidence / b.cells.len() as f64).total_cmp(&(a.confidence / a.cells.len() as f64)));
    }
    let depth_guided = rules.edge_depth_m > 0.0
        && map.depth.len() == map.labels.len()
        && frame.depth.len() == frame.width * frame.height;
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
        let scaled = if depth_guided {
            depth_guided_mask(map, &instance, frame, rules.edge_depth_m)
        } else {
            block_mask(map, &instance, frame.width, frame.height)
        };
        // A frame smaller than the map leaves some cells without a pixel.
        let Some((bbox, mask)) = scaled else {
            dropped += 1;
            continue;
        };
        objects.push(DetectedObject { obj_id, instance: *count as u32, score, bbox, mask });
        *count += 1;
    }
    Found { objects, dropped }
}

/// A box and the mask inside it, `x, y, width, height` in frame pixels.
type FrameMask = ([u32; 4], Vec<bool>);

/// Which cells of the map are the region's.
pub(crate) fn membership(map: &LabelMap, region: &Region) -> Vec<bool> {
    let mut inside = vec![false; map.width * map.height];
    for &c in &region.cells {
        inside[c] = true;
    }
    inside
}

/// Frame pixels `first(c0)..first(c1 + 1)` are those whose cell
/// `floor(u·cells/pixels)` lies in `c0..=c1`.
fn pixel_span(c0: usize, c1: usize, cells: usize, pixels: usize) -> (usize, usize) {
    let first = |cell: usize| (cell * pixels).div_ceil(cells);
    (first(c0), first(c1 + 1).min(pixels))
}

/// Scales a region up block by block: the frame pixels whose nearest map
/// cell (the one whose block holds them) is in the region. `None` when no
/// pixel is.
fn block_mask(map: &LabelMap, region: &Region, fw: usize, fh: usize) -> Option<FrameMask> {
    let (w, h) = (map.width, map.height);
    let inside = membership(map, region);
    let [cx0, cy0, cx1, cy1] = region.bounds;
    let (x0, x1) = pixel_span(cx0, cx1, w, fw);
    let (y0, y1) = pixel_span(cy0, cy1, h, fh);
    let mut mask = Vec::with_capacity((x1 - x0) * (y1 - y0));
    for v in y0..y1 {
        let cy = v * h / fh;
        for u in x0..x1 {
            mask.push(inside[cy * w + u * w / fw]);
        }
    }
    mask.contains(&true).then(|| ([x0 as u32, y0 as u32, (x1 - x0) as u32, (y1 - y0) as u32], mask))
}

/// Scales a region up pixel by pixel: each frame pixel within a cell of the
/// region's cells is the region's when the vote of its four nearest cells,
/// weighted bilinearly and by `exp(−½ (Δz / edge_depth)²)` for the depth
/// difference between pixel and cell, is over half for the region. A pixel
/// or cell without depth votes by position alone; a pixel whose depth
/// matches none of its cells goes with the cell whose block holds it. The
/// box is the mask's tight box; `None` when no pixel is the region's.
fn depth_guided_mask(map: &LabelMap, region: &Region, frame: &FrameGrid<'_>, edge_depth: f32) -> Option<FrameMask> {
    let (w, h) = (map.width, map.height);
    let (fw, fh) = (frame.width, frame.height);
    let inside = membership(map, region);
    let [cx0, cy0, cx1, cy1] = region.bounds;
    // A pixel of a block next to the region can still be on its surface.
    let (x0, x1) = pixel_span(cx0.saturating_sub(1), (cx1 + 1).min(w - 1), w, fw);
    let (y0, y1) = pixel_span(cy0.saturating_sub(1), (cy1 + 1).min(h - 1), h, fh);
    let (sx, sy) = (w as f32 / fw as f32, h as f32 / fh as f32);
    let inv_two_var = 0.5 / (edge_depth * edge_depth);
    let (mut bx0, mut by0, mut bx1, mut by1) = (usize::MAX, usize::MAX, 0, 0);
    let mut full = vec![false; (x1 - x0) * (y1 - y0)];
    for v in y0..y1 {
        // Continuous cell coordinates: cell c's centre is at c.
        let gy = ((v as f32 + 0.5) * sy - 0.5).clamp(0.0, (h - 1) as f32);
        let (ya, fy) = (gy.floor() as usize, gy.fract());
        let yb = (ya + 1).min(h - 1);
        for u in x0..x1 {
            let gx = ((u as f32 + 0.5) * sx - 0.5).clamp(0.0, (w - 1) as f32);
            let (xa, fx) = (gx.floor() as usize, gx.fract());
            let xb = (xa + 1).min(w - 1);
            let z = frame.depth[v * fw + u];
            let (mut total, mut ours) = (0.0f32, 0.0f32);
            for (cell, spatial) in [
                (ya * w + xa, (1.0 - fx) * (1.0 - fy)),
                (ya * w + xb, fx * (1.0 - fy)),
                (yb * w + xa, (1.0 - fx) * fy),
                (yb * w + xb, fx * fy),
            ] {
                let zc = map.depth[cell];
                let similar = if z > 0.0 && zc > 0.0 { (-(z - zc) * (z - zc) * inv_two_var).exp() } else { 1.0 };
                total += spatial * similar;
                if inside[cell] {
                    ours += spatial * similar;
                }
            }
            let member = if total > 1e-6 { ours > 0.5 * total } else { inside[(v * h / fh) * w + u * w / fw] };
            if member {
                full[(v - y0) * (x1 - x0) + (u - x0)] = true;
                (bx0, by0, bx1, by1) = (bx0.min(u), by0.min(v), bx1.max(u), by1.max(v));
            }
        }
    }
    if bx0 == usize::MAX {
        return None;
    }
    let mut mask = Vec::with_capacity((bx1 - bx0 + 1) * (by1 - by0 + 1));
    for v in by0..=by1 {
        let row = (v - y0) * (x1 - x0);
        mask.extend_from_slice(&full[row + bx0 - x0..=row + bx1 - x0]);
    }
    Some(([bx0 as u32, by0 as u32, (bx1 - bx0 + 1) as u32, (by1 - by0 + 1) as u32], mask))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn frame(width: usize, height: usize) -> FrameGrid<'static> {
        FrameGrid { width, height, depth: &[] }
    }

    const RULES: InstanceRules = InstanceRules {
        min_pixels: 16,
        merge_gap_px: 8,
        max_instances: 1,
        min_score: 0.3,
        edge_depth_m: 0.0,
        most_confident_first: false,
    };

    fn map_with(width: usize, height: usize, boxes: &[(u8, [usize; 4])]) -> LabelMap {
        let mut labels = vec![0; width * height];
        for &(class, [x0, y0, x1, y1]) in boxes {
            for y in y0..=y1 {
                for x in x0..=x1 {
                    labels[y * width + x] = class;
                }
            }
        }
        LabelMap {
            width,
            height,
            confidence: vec![0.9; width * height],
            labels,
            depth: Vec::new(),
            instances: Vec::new(),
        }
    }

    #[test]
    fn a_square_region_scales_to_its_frame_box_and_mask() {
        // Cells 2..=3 of a 10-wide map over a 40-wide frame: pixels 8..16.
        let map = map_with(10, 10, &[(1, [2, 2, 3, 3])]);
        let found = detections(&map, &[7], &frame(40, 40), &RULES);
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
        let one = detections(&map, &[3], &frame(80, 40), &RULES);
        assert_eq!((one.objects.len(), one.dropped), (1, 1));
        assert_eq!(one.objects[0].bbox, [0, 0, 24, 12]);
        // The gap between the merged pieces is not in the mask.
        assert!(!one.objects[0].mask[12]);
        let two = detections(&map, &[3], &frame(80, 40), &InstanceRules { max_instances: 2, ..RULES });
        assert_eq!(two.objects.iter().map(|o| o.instance).collect::<Vec<_>>(), [0, 1]);
    }

    #[test]
    fn given_instances_are_kept_apart_and_whole() {
        // Instance 1: two pieces of object 1 far apart (one object seen in
        // two clusters); instance 2, object 1 again, touching the first
        // piece: not merged with it, as regions would be.
        let mut map = map_with(20, 10, &[(1, [0, 0, 2, 2]), (1, [3, 0, 4, 2]), (1, [15, 5, 16, 6])]);
        map.instances = vec![0; 200];
        for (i, label) in map.labels.iter().enumerate() {
            if *label != 0 {
                map.instances[i] = if (3..=4).contains(&(i % 20)) { 2 } else { 1 };
            }
        }
        let rules = InstanceRules { max_instances: 2, ..RULES };
        let found = detections(&map, &[5], &frame(80, 40), &rules);
        assert_eq!(found.dropped, 0);
        let boxes: Vec<[u32; 4]> = found.objects.iter().map(|o| o.bbox).collect();
        assert_eq!(boxes, [[0, 0, 68, 28], [12, 0, 8, 12]], "{found:?}");
    }

    #[test]
    fn the_most_confident_instance_wins_when_asked() {
        // A large unsure region and a small sure one of the same object.
        let mut map = map_with(20, 10, &[(1, [0, 0, 5, 5]), (1, [15, 0, 16, 1])]);
        for (i, c) in map.confidence.iter_mut().enumerate() {
            *c = if i % 20 >= 15 { 0.95 } else { 0.5 };
        }
        let largest = detections(&map, &[2], &frame(80, 40), &RULES);
        assert_eq!(largest.objects[0].bbox, [0, 0, 24, 24]);
        let surest = detections(&map, &[2], &frame(80, 40), &InstanceRules { most_confident_first: true, ..RULES });
        assert_eq!(surest.objects[0].bbox, [60, 0, 8, 8]);
        assert_eq!((surest.objects.len(), surest.dropped), (1, 1));
    }

    #[test]
    fn small_and_unsure_regions_are_dropped_and_counted() {
        let mut map = map_with(10, 10, &[(1, [0, 0, 0, 0]), (2, [5, 5, 8, 8])]);
        map.confidence.iter_mut().for_each(|c| *c = 0.2);
        let found = detections(&map, &[1, 2], &frame(40, 40), &RULES);
        assert_eq!((found.objects.len(), found.dropped), (0, 2));
    }

    #[test]
    fn depth_guided_masks_follow_the_surface_across_block_edges() {
        // Cells 0 and 1 of a 4 × 1 map are the object (depth 0.5 m), 2 and
        // 3 the table (0.8 m) over a 16 × 4 frame; the object's surface
        // reaches two pixels into cell 2's block, which the block mask
        // misses and the depth-guided one takes.
        let mut map = map_with(4, 1, &[(1, [0, 0, 1, 0])]);
        map.depth = vec![0.5, 0.5, 0.8, 0.8];
        let depth: Vec<f32> = (0..64).map(|i| if i % 16 <= 9 { 0.5 } else { 0.8 }).collect();
        let frame = FrameGrid { width: 16, height: 4, depth: &depth };
        let blocks = detections(&map, &[7], &frame, &RULES);
        assert_eq!(blocks.objects[0].bbox, [0, 0, 8, 4]);
        let guided = detections(&map, &[7], &frame, &InstanceRules { edge_depth_m: 0.01, ..RULES });
        let [object] = guided.objects.as_slice() else { panic!("{guided:?}") };
        assert_eq!(object.bbox, [0, 0, 10, 4]);
        assert!(object.mask.iter().all(|&m| m));
        // And the other way: the table seen through the object's last block.
        let depth: Vec<f32> = (0..64).map(|i| if i % 16 <= 5 { 0.5 } else { 0.8 }).collect();
        let frame = FrameGrid { width: 16, height: 4, depth: &depth };
        let guided = detections(&map, &[7], &frame, &InstanceRules { edge_depth_m: 0.01, ..RULES });
        assert_eq!(guided.objects[0].bbox, [0, 0, 6, 4]);
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
            let map = LabelMap { width: 8, height: 6, confidence: vec![1.0; 48], labels: cells, depth: Vec::new(), instances: Vec::new() };
            let rules = InstanceRules { min_pixels: 1, merge_gap_px: 0, max_instances: 100, min_score: 0.0, ..RULES };
            let found = detections(&map, &[1, 2], &frame(fw, fh), &rules);
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

        /// Where each pixel has the depth of the cell whose block holds it
        /// and cells' depths are far apart, a pixel's vote is its own
        /// block's: the depth-guided masks are the block masks.
        #[test]
        fn depth_guided_masks_are_block_masks_when_each_block_is_its_own_surface(
            cells in proptest::collection::vec(0u8..3, 8 * 6),
            (fw, fh) in (8usize..64, 6usize..48),
        ) {
            let cell_depth: Vec<f32> = (0..48).map(|c| 0.5 + 0.05 * c as f32).collect();
            let depth: Vec<f32> = (0..fw * fh).map(|i| cell_depth[(i / fw) * 6 / fh * 8 + (i % fw) * 8 / fw]).collect();
            let map = LabelMap { width: 8, height: 6, confidence: vec![1.0; 48], labels: cells, depth: cell_depth, instances: Vec::new() };
            let rules = InstanceRules { min_pixels: 1, merge_gap_px: 0, max_instances: 100, min_score: 0.0, ..RULES };
            let frame = FrameGrid { width: fw, height: fh, depth: &depth };
            let blocks = detections(&map, &[1, 2], &frame, &rules);
            let guided = detections(&map, &[1, 2], &frame, &InstanceRules { edge_depth_m: 0.002, ..rules });
            prop_assert_eq!(blocks, guided);
        }
    }
}
