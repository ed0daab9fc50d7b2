//! A static 3D k-d tree (implicit, median-split) for ICP's nearest-neighbour queries.

use nalgebra::Vector3;

pub(crate) struct KdTree<'a> {
    pts: &'a [Vector3<f64>],
    /// Point indices arranged so that every range [lo, hi) has its split point at its middle.
    idx: Vec<u32>,
    /// Split axis of the node whose median sits at this position of `idx`.
    axis: Vec<u8>,
}

impl<'a> KdTree<'a> {
    pub(crate) fn new(pts: &'a [Vector3<f64>]) -> Self {
        let mut t = Self {
            pts,
            idx: (0..pts.len() as u32).collect(),
            axis: vec![0; pts.len()],
        };
        t.build(0, pts.len());
        t
    }

    fn build(&mut self, lo: usize, hi: usize) {
        if hi <= lo + 1 {
            return;
        }
        let (mut mn, mut mx) = (
            Vector3::repeat(f64::INFINITY),
            Vector3::repeat(f64::NEG_INFINITY),
        );
        for &i in &self.idx[lo..hi] {
            mn = mn.inf(&self.pts[i as usize]);
            mx = mx.sup(&self.pts[i as usize]);
        }
        let axis = (mx - mn).imax();
        let mid = (lo + hi) / 2;
        let pts = self.pts;
        self.idx[lo..hi].select_nth_unstable_by(mid - lo, |a, b| {
            pts[*a as usize][axis].total_cmp(&pts[*b as usize][axis])
        });
        self.axis[mid] = axis as u8;
        self.build(lo, mid);
        self.build(mid + 1, hi);
    }

    /// Index and squared distance of the point nearest to `q` within `max_d2`, if any.
    pub(crate) fn nearest(&self, q: &Vector3<f64>, max_d2: f64) -> Option<(usize, f64)> {
        let mut best = (usize::MAX, max_d2);
        self.search(0, self.pts.len(), q, &mut best);
        (best.0 != usize::MAX).then_some(best)
    }

    fn search(&self, lo: usize, hi: usize, q: &Vector3<f64>, best: &mut (usize, f64)) {
        if lo >= hi {
            return;
        }
        let mid = (lo + hi) / 2;
        let i = self.idx[mid] as usize;
        let d2 = (self.pts[i] - q).norm_squared();
        if d2 < best.1 {
            *best = (i, d2);
        }
        if hi - lo == 1 {
            return;
        }
        let axis = self.axis[mid] as usize;
        let diff = q[axis] - self.pts[i][axis];
        let (near, far) = if diff < 0.0 {
            ((lo, mid), (mid + 1, hi))
        } else {
            ((mid + 1, hi), (lo, mid))
        };
        self.search(near.0, near.1, q, best);
        if diff * diff < best.1 {
            self.search(far.0, far.1, q, best);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn agrees_with_linear_search() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let pts: Vec<Vector3<f64>> = (0..500)
            .map(|_| {
                Vector3::new(
                    rng.gen_range(-5.0..5.0),
                    rng.gen_range(-5.0..5.0),
                    rng.gen_range(0.0..1.0),
                )
            })
            .collect();
        let tree = KdTree::new(&pts);
        for _ in 0..200 {
            let q = Vector3::new(
                rng.gen_range(-6.0..6.0),
                rng.gen_range(-6.0..6.0),
                rng.gen_range(-1.0..2.0),
            );
            let (bi, bd) = pts
                .iter()
                .enumerate()
                .map(|(i, p)| (i, (p - q).norm_squared()))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            let (ti, td) = tree.nearest(&q, f64::INFINITY).unwrap();
            assert!((td - bd).abs() < 1e-12 && (ti == bi || td == bd));
        }
        assert!(tree.nearest(&Vector3::new(100.0, 0.0, 0.0), 1.0).is_none());
    }
}
