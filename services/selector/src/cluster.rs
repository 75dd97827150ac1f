//! DBSCAN over pose samples with the paper's neighbourhood: two poses are
//! neighbours when their geodesic rotation angle is at most ε_R **and**
//! their translations are at most ε_t apart.

use poseflow_geometry::{Pose, so3};

/// Cluster labels of a set of poses; clusters are numbered by size, the
/// largest first (ties: the one whose first member comes first).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Clusters {
    /// Per pose, its cluster, or `None` for noise.
    pub labels: Vec<Option<usize>>,
    /// Members per cluster, in cluster order.
    pub sizes: Vec<usize>,
}

impl Clusters {
    pub fn members(&self, cluster: usize) -> impl Iterator<Item = usize> + '_ {
        self.labels.iter().enumerate().filter(move |(_, l)| **l == Some(cluster)).map(|(i, _)| i)
    }
}

/// The DBSCAN neighbourhood.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Neighbourhood {
    /// ε_R, radians.
    pub rotation: f64,
    /// ε_t, metres.
    pub translation: f64,
    /// Neighbours (the pose itself included) that make a core pose.
    pub min_samples: usize,
}

impl Neighbourhood {
    fn near(&self, a: &Pose, b: &Pose) -> bool {
        (a.translation - b.translation).norm() <= self.translation
            && so3::geodesic_angle(&a.rotation, &b.rotation) <= self.rotation
    }
}

/// Density-based clusters (Ester et al., 1996). O(N²) distance tests: N is
/// the sample count (50 by default).
pub fn dbscan(poses: &[Pose], neighbourhood: &Neighbourhood) -> Clusters {
    let n = poses.len();
    let neighbours: Vec<Vec<usize>> =
        (0..n).map(|i| (0..n).filter(|&j| neighbourhood.near(&poses[i], &poses[j])).collect()).collect();
    let core: Vec<bool> = neighbours.iter().map(|list| list.len() >= neighbourhood.min_samples).collect();
    let mut raw: Vec<Option<usize>> = vec![None; n];
    let mut count = 0;
    for seed in 0..n {
        if raw[seed].is_some() || !core[seed] {
            continue;
        }
        raw[seed] = Some(count);
        let mut frontier = vec![seed];
        while let Some(i) = frontier.pop() {
            if !core[i] {
                continue;
            }
            for &j in &neighbours[i] {
                if raw[j].is_none() {
                    raw[j] = Some(count);
                    frontier.push(j);
                }
            }
        }
        count += 1;
    }
    // Renumber by size (stable: equal sizes keep discovery order).
    let mut sizes = vec![0usize; count];
    for label in raw.iter().flatten() {
        sizes[*label] += 1;
    }
    let mut order: Vec<usize> = (0..count).collect();
    order.sort_by(|a, b| sizes[*b].cmp(&sizes[*a]));
    let mut rank = vec![0; count];
    for (new, old) in order.iter().enumerate() {
        rank[*old] = new;
    }
    Clusters {
        labels: raw.iter().map(|l| l.map(|old| rank[old])).collect(),
        sizes: order.iter().map(|old| sizes[*old]).collect(),
    }
}
