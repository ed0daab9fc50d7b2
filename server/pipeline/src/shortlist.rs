//! A deeper shortlist: the global descriptor's top `depth` map images re-ranked by votes of their
//! strongest keypoints, before the geometric stage takes the best few.
//!
//! Why: one aggregated vector per image (VLAD) ranks look-alike rooms of a large map close together.
//! On a map of HPointLoc-All size (10,500 images of 35 procedural apartments) the right Point is
//! among VLAD's first 5 for 0.73 of the queries but among its first 100 for 0.94.
//!
//! A vote: mutual nearest neighbours between the query's and the image's strongest keypoints,
//! scored by how many of those matches agree with one another in 3D: the highest core number of
//! the registration's consistency graph (the largest `k` such that some matches each agree with
//! `k` of the others). Three votes, each with more keypoints over the best of the one before:
//! 128 keypoints over every candidate, 256 over the best 20, 512 over the best 10 with the
//! registration's own bound. On that map the right Point is among the first 5 for 0.84 by
//! counting matches, 0.87 after the first vote, 0.91 after the third (BENCHMARKS.md, "A deeper
//! shortlist" and "Three votes"). Re-ranking a global shortlist by local matches is the classic
//! second stage of image retrieval (Philbin et al., CVPR 2007, with a spatial check); the core
//! number is a cheap upper bound of TEASER's maximum clique, so the geometric stage after it checks
//! the survivors properly.
//!
//! Cost: one `k x k` similarity product per image voted on (`k` = [`COARSE_KEYPOINTS`], about 0.1
//! ms on one core; [`SHORTLIST_KEYPOINTS`] in the second vote, about 0.35 ms; [`FINAL_KEYPOINTS`]
//! in the third, whose 10 images add about 2 ms a query). The depth grows with the square root of the map's size
//! ([`automatic_depth`]): a one-apartment map votes on 20 images, then on its best 10; a
//! 10,000-image map on 100, 20 and 10.

use nalgebra::Vector3;
use pntr_features::mnn::{mutual_nearest, Mnn, MnnBuffers};
use pntr_features::{Features, Matcher, Matches};
use pntr_registration::teaser::consistency_graph;
use pntr_retrieval::index::Hit;

use crate::map::MapImage;
use crate::PipelineError;

/// Keypoints per image (the strongest by detection score) of the first vote, over every candidate.
pub const COARSE_KEYPOINTS: usize = 128;

/// Keypoints per image of the second vote, over the first's best `FINE_FACTOR * keep`.
pub const SHORTLIST_KEYPOINTS: usize = 256;

/// How many of the first vote's best, per candidate kept, the second vote looks at again (when the
/// first had more than that many).
pub const FINE_FACTOR: usize = 4;

/// Keypoints per image of the third vote (every keypoint a default map stores), over the second's
/// best `FINAL_FACTOR * keep`, with the registration's own bound (half the others').
pub const FINAL_KEYPOINTS: usize = 512;

/// How many of the second vote's best, per candidate kept, the third vote looks at again.
pub const FINAL_FACTOR: usize = 2;

/// Most map images the automatic depth votes on, whatever the map's size (about 13 ms a query on
/// one core); a preset's explicit `shortlist` is taken as it is.
pub const MAX_DEPTH: usize = 128;

/// How many global candidates to re-rank when the preset leaves it automatic: the square root of
/// the map's image count (the global rank of the right Point grows with the number of look-alikes),
/// at least four times the `keep` candidates that go on, at most [`MAX_DEPTH`] and the map's size.
pub fn automatic_depth(map_images: usize, keep: usize) -> usize {
    let by_size = (map_images as f64).sqrt().round() as usize;
    by_size.max(4 * keep).min(MAX_DEPTH).min(map_images)
}

/// The shortlist's candidates, with the vote's matches where they are the whole features'.
#[derive(Debug, Clone, Default)]
pub struct Shortlisted {
    /// The candidates kept, best first, with their global scores.
    pub hits: Vec<Hit>,
    /// Aligned with `hits`: where the last vote compared every keypoint of the query and of the
    /// image, its matches as the matcher gives them on the whole features (`(query, image)`
    /// keypoint indices, query index ascending), so the geometric stage need not match that
    /// pair again; `None` where the vote saw only the strongest keypoints.
    pub matches: Vec<Option<Matches>>,
}

impl Shortlisted {
    /// Candidates without known matches (not voted on, or fewer than wanted).
    pub fn unmatched(hits: Vec<Hit>) -> Self {
        let matches = vec![None; hits.len()];
        Self { hits, matches }
    }
}

/// The strongest keypoints of every map image, chosen once when the pipeline is made.
#[derive(Debug, Clone, Default)]
pub struct Shortlist {
    /// Per map image (map order), indices of its strongest keypoints, best first.
    strongest: Vec<Vec<u16>>,
    keypoints: usize,
}

/// Indices of the `n` highest `scores`, best first (ties keep the lower index first).
fn strongest_indices(scores: &[f32], n: usize) -> Vec<u16> {
    let mut order: Vec<u16> = (0..scores.len().min(u16::MAX as usize) as u16).collect();
    // Ties by index: the order of a stable sort.
    order.sort_unstable_by(|&a, &b| {
        scores[b as usize]
            .total_cmp(&scores[a as usize])
            .then(a.cmp(&b))
    });
    order.truncate(n);
    order
}

/// The features of `f` at `indices` (float or binary descriptors, whichever `f` has).
fn gather(f: &Features, indices: &[u16]) -> Features {
    let pick = |i: &u16| *i as usize;
    Features {
        keypoints: indices.iter().map(|i| f.keypoints[pick(i)]).collect(),
        scores: indices.iter().map(|i| f.scores[pick(i)]).collect(),
        descriptors: if f.descriptors.is_empty() {
            Vec::new()
        } else {
            indices
                .iter()
                .flat_map(|i| f.descriptor(pick(i)).iter().copied())
                .collect()
        },
        dim: f.dim,
        binary: if f.binary.is_empty() {
            Vec::new()
        } else {
            indices.iter().map(|i| f.binary[pick(i)]).collect()
        },
        image_size: f.image_size,
    }
}

/// The map image's features at `indices`, descriptors widened from f16.
fn gather_map(im: &MapImage, indices: &[u16]) -> Features {
    let mut descriptors = vec![
        0f32;
        if im.dim > 0 && !im.descriptors.is_empty() {
            indices.len() * im.dim
        } else {
            0
        }
    ];
    if !descriptors.is_empty() {
        use half::slice::HalfFloatSliceExt;
        for (row, &i) in descriptors.chunks_exact_mut(im.dim).zip(indices) {
            let i = i as usize;
            im.descriptors[i * im.dim..(i + 1) * im.dim].convert_to_f32_slice(row);
        }
    }
    Features {
        keypoints: indices.iter().map(|&i| im.keypoints[i as usize]).collect(),
        scores: indices.iter().map(|&i| im.scores[i as usize]).collect(),
        descriptors,
        dim: im.dim,
        binary: if im.binary.is_empty() {
            Vec::new()
        } else {
            indices.iter().map(|&i| im.binary[i as usize]).collect()
        },
        image_size: im.image_size,
    }
}

/// Buffers one pass of votes reuses from image to image.
#[derive(Default)]
struct Scratch {
    /// The map image's strongest descriptors, widened to f32, one row each.
    db: Vec<f32>,
    mnn: MnnBuffers,
    matches: Matches,
    src: Vec<Vector3<f64>>,
    dst: Vec<Vector3<f64>>,
}

/// One vote: the mutual matches of the query's strongest keypoints (`q`, with their 3D points
/// `q_points`) with the map image's at `indices`, scored by geometric consistency: the largest `k`
/// such that some matches each agree with at least `k` of the others (their 3D distances agree
/// with the query's within `bound_m`), the highest core number of TEASER's consistency graph, then
/// the number of matches. The core number bounds the maximum clique (TEASER's inlier set) from
/// above and, unlike one match's degree, is not raised by a match that agrees with many others
/// that disagree among themselves. An image or query without keypoints gets no votes.
fn vote(
    q: &Features,
    q_points: &[Option<Vector3<f64>>],
    im: &MapImage,
    indices: &[u16],
    matcher: &Mnn,
    bound_m: f64,
    s: &mut Scratch,
) -> Result<(usize, usize), PipelineError> {
    if q.is_empty() || indices.is_empty() {
        return Ok((0, 0));
    }
    let float = q.binary.is_empty() && q.dim > 0 && !q.descriptors.is_empty() && q.dim == im.dim;
    s.matches.pairs.clear();
    s.matches.scores.clear();
    if float && im.descriptors.len() >= im.keypoints.len() * im.dim {
        // The map image's rows widened into a reused buffer, matched without allocating.
        use half::slice::HalfFloatSliceExt;
        let dim = im.dim;
        s.db.resize(indices.len() * dim, 0.0);
        for (row, &i) in s.db.chunks_exact_mut(dim).zip(indices) {
            let i = i as usize;
            im.descriptors[i * dim..(i + 1) * dim].convert_to_f32_slice(row);
        }
        mutual_nearest(
            &q.descriptors,
            &s.db,
            dim,
            &matcher.params,
            &mut s.mnn,
            &mut s.matches,
        );
    } else {
        s.matches = matcher.match_features(q, &gather_map(im, indices))?;
    }
    s.src.clear();
    s.dst.clear();
    for &(i, j) in &s.matches.pairs {
        if let (Some(Some(a)), Some(b)) = (
            q_points.get(i as usize),
            im.point(indices[j as usize] as usize),
        ) {
            s.src.push(*a);
            s.dst.push(b);
        }
    }
    let finite = vec![true; s.src.len()];
    let g = consistency_graph(&s.src, &s.dst, &finite, bound_m);
    let core = g.core_numbers().into_iter().max().unwrap_or(0);
    Ok((core, s.matches.pairs.len()))
}

impl Shortlist {
    /// Choose the `keypoints` strongest keypoints of each of `images`.
    pub fn new(images: &[MapImage], keypoints: usize) -> Self {
        Self {
            strongest: images
                .iter()
                .map(|im| strongest_indices(&im.scores, keypoints))
                .collect(),
            keypoints,
        }
    }

    /// `hits` (candidates, best first) re-ordered by one vote (see [`Shortlist::rerank`]) with the
    /// `keypoints` strongest keypoints, best first, the order of `hits` breaking ties.
    ///
    /// Errors: as [`Shortlist::rerank`].
    #[allow(clippy::too_many_arguments)]
    pub fn ranked_by_vote(
        &self,
        images: &[MapImage],
        query: &Features,
        query_points: &[Option<Vector3<f64>>],
        hits: &[Hit],
        keypoints: usize,
        matcher: &Mnn,
        bound_m: f64,
    ) -> Result<Vec<Hit>, PipelineError> {
        let voted = self.voted(
            images,
            query,
            query_points,
            hits,
            keypoints,
            matcher,
            bound_m,
            false,
        )?;
        Ok(voted.into_iter().map(|v| v.0).collect())
    }

    /// [`Shortlist::ranked_by_vote`], each hit with the vote's matches in the features' own
    /// indices when `record` is set and the vote compared every keypoint of both sides.
    #[allow(clippy::too_many_arguments)]
    fn voted(
        &self,
        images: &[MapImage],
        query: &Features,
        query_points: &[Option<Vector3<f64>>],
        hits: &[Hit],
        keypoints: usize,
        matcher: &Mnn,
        bound_m: f64,
        record: bool,
    ) -> Result<Vec<(Hit, Option<Matches>)>, PipelineError> {
        let order = strongest_indices(&query.scores, keypoints);
        let q = gather(query, &order);
        let q_points: Vec<Option<Vector3<f64>>> = order
            .iter()
            .map(|&i| query_points.get(i as usize).copied().flatten())
            .collect();
        let mut voted = Vec::with_capacity(hits.len());
        let mut scratch = Scratch::default();
        for (rank, h) in hits.iter().enumerate() {
            let (Some(im), Some(idx)) = (images.get(h.id), self.strongest.get(h.id)) else {
                return Err(PipelineError::Config(format!(
                    "retrieval returned image {} of a map of {}",
                    h.id,
                    images.len()
                )));
            };
            let idx = &idx[..idx.len().min(keypoints)];
            let v = vote(&q, &q_points, im, idx, matcher, bound_m, &mut scratch)?;
            let whole = record && order.len() == query.len() && idx.len() == im.keypoints.len();
            let matches = whole.then(|| {
                // Back to the features' own indices, in the order the matcher gives them.
                let mut m: Vec<((u32, u32), f32)> = scratch
                    .matches
                    .pairs
                    .iter()
                    .zip(&scratch.matches.scores)
                    .map(|(&(a, b), &s)| ((order[a as usize] as u32, idx[b as usize] as u32), s))
                    .collect();
                // Unique keys (one match per query keypoint): the unstable sort's order is the stable one's.
                m.sort_unstable_by_key(|p| p.0);
                Matches {
                    pairs: m.iter().map(|p| p.0).collect(),
                    scores: m.iter().map(|p| p.1).collect(),
                }
            });
            voted.push((v, rank, *h, matches));
        }
        voted.sort_unstable_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        Ok(voted.into_iter().map(|v| (v.2, v.3)).collect())
    }

    /// The best `keep` of `hits` (global candidates, best first), with their global scores: all
    /// are voted on with [`COARSE_KEYPOINTS`] keypoints, the best `FINE_FACTOR * keep` again with
    /// the (up to) [`SHORTLIST_KEYPOINTS`] strongest, the best `FINAL_FACTOR * keep` of those a
    /// third time with (up to) [`FINAL_KEYPOINTS`] and half the bound; a later vote runs only when
    /// the list before it is longer than it keeps. A vote ([`vote`]) scores the mutual matches of
    /// the query's and the image's strongest keypoints by how many agree with each other in 3D
    /// within `bound_m` (metres; the registration's consistency bound); `query_points` are the
    /// query's keypoints back-projected (OpenCV camera frame, `None` without depth).
    ///
    /// Errors: a hit outside `images`, or descriptors the matcher cannot compare (another
    /// extractor's).
    #[allow(clippy::too_many_arguments)]
    pub fn rerank(
        &self,
        images: &[MapImage],
        query: &Features,
        query_points: &[Option<Vector3<f64>>],
        hits: &[Hit],
        keep: usize,
        matcher: &Mnn,
        bound_m: f64,
    ) -> Result<Vec<Hit>, PipelineError> {
        let kept =
            self.rerank_matched(images, query, query_points, hits, keep, matcher, bound_m)?;
        Ok(kept.hits)
    }

    /// [`Shortlist::rerank`], with the last vote's matches of each candidate kept where they are
    /// the whole features' ([`Shortlisted::matches`]).
    ///
    /// Errors: as [`Shortlist::rerank`].
    #[allow(clippy::too_many_arguments)]
    pub fn rerank_matched(
        &self,
        images: &[MapImage],
        query: &Features,
        query_points: &[Option<Vector3<f64>>],
        hits: &[Hit],
        keep: usize,
        matcher: &Mnn,
        bound_m: f64,
    ) -> Result<Shortlisted, PipelineError> {
        let coarse = COARSE_KEYPOINTS.min(self.keypoints);
        let mut ranked = self.voted(
            images,
            query,
            query_points,
            hits,
            coarse,
            matcher,
            bound_m,
            true,
        )?;
        // Each later vote looks again, with more keypoints, at the best of the one before; on a
        // small map the first vote saw every candidate worth the second look already.
        let later = [
            (FINE_FACTOR * keep, SHORTLIST_KEYPOINTS, bound_m),
            (FINAL_FACTOR * keep, FINAL_KEYPOINTS, 0.5 * bound_m),
        ];
        for (look_again, keypoints, bound_m) in later {
            if ranked.len() <= look_again {
                continue;
            }
            let best: Vec<Hit> = ranked[..look_again].iter().map(|v| v.0).collect();
            ranked = self.voted(
                images,
                query,
                query_points,
                &best,
                keypoints.min(self.keypoints),
                matcher,
                bound_m,
                true,
            )?;
        }
        ranked.truncate(keep);
        let (hits, matches) = ranked.into_iter().unzip();
        Ok(Shortlisted { hits, matches })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn automatic_depth_grows_with_the_map_within_bounds() {
        assert_eq!(automatic_depth(138, 5), 20);
        assert_eq!(automatic_depth(10_500, 5), 102);
        assert_eq!(automatic_depth(1_000_000, 5), MAX_DEPTH);
        assert_eq!(automatic_depth(12, 5), 12);
    }

    /// `n` unit descriptors of 64 dimensions from a seeded generator.
    fn descriptors(n: usize, seed: u64) -> Vec<f32> {
        let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut out = Vec::with_capacity(n * 64);
        for _ in 0..n {
            let row: Vec<f32> = (0..64)
                .map(|_| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
                })
                .collect();
            let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
            out.extend(row.iter().map(|x| x / norm));
        }
        out
    }

    fn features(desc: Vec<f32>, scores: Vec<f32>) -> Features {
        Features {
            keypoints: (0..scores.len()).map(|i| [i as f32, 0.0]).collect(),
            scores,
            descriptors: desc,
            dim: 64,
            binary: Vec::new(),
            image_size: (256, 256),
        }
    }

    fn map_image(f: &Features) -> MapImage {
        MapImage {
            id: String::new(),
            scene: 0,
            point: 0,
            world_from_camera: nalgebra::Isometry3::identity(),
            stamp: None,
            keypoints: f.keypoints.clone(),
            scores: f.scores.clone(),
            descriptors: f
                .descriptors
                .iter()
                .map(|&x| half::f16::from_f32(x))
                .collect(),
            dim: 64,
            binary: Vec::new(),
            points: vec![[f32::NAN; 3]; f.len()],
            instances: vec![0; f.len()],
            image_size: f.image_size,
            camera: pntr_core::Intrinsics::hpointloc(),
            thumb: crate::verify::Thumb::new(
                &pntr_core::RgbImage {
                    width: 16,
                    height: 16,
                    data: vec![0; 16 * 16 * 3],
                },
                &pntr_core::DepthMap {
                    width: 16,
                    height: 16,
                    data: vec![1.0; 16 * 16],
                },
                &pntr_core::Intrinsics::hpointloc(),
            ),
            fine: None,
        }
    }

    #[test]
    fn the_image_sharing_the_strongest_keypoints_comes_first() {
        // The query's 40 descriptors; image 2 holds them all (as its strongest), image 1 holds
        // them only among its weakest keypoints (beyond the vote's 32), image 0 none.
        let q = features(descriptors(40, 1), vec![1.0; 40]);
        let strangers = descriptors(60, 2);
        let shared_strong = {
            let mut d = q.descriptors.clone();
            d.extend_from_slice(&strangers[..20 * 64]);
            features(d, (0..60).map(|i| 1.0 - i as f32 / 100.0).collect())
        };
        let shared_weak = {
            let mut d = strangers[..20 * 64].to_vec();
            d.extend_from_slice(&q.descriptors);
            features(d, (0..60).map(|i| 1.0 - i as f32 / 100.0).collect())
        };
        let images = vec![
            map_image(&features(strangers.clone(), vec![0.5; 60])),
            map_image(&shared_weak),
            map_image(&shared_strong),
        ];
        let hits: Vec<Hit> = (0..3)
            .map(|id| Hit {
                id,
                score: 1.0 - id as f32 / 10.0,
            })
            .collect();
        let list = Shortlist::new(&images, 32);
        let kept = list
            .rerank(&images, &q, &[], &hits, 2, &Mnn::default(), 0.1)
            .unwrap();
        let ids: Vec<usize> = kept.iter().map(|h| h.id).collect();
        assert_eq!(ids, vec![2, 1], "votes 32 > 12 > 0");
        // Global scores travel with their images.
        assert_eq!(kept[0].score, hits[2].score);
        // A hit the map does not have is an error, not a panic.
        let bad = [Hit { id: 9, score: 1.0 }];
        assert!(list
            .rerank(&images, &q, &[], &bad, 1, &Mnn::default(), 0.1)
            .is_err());
    }

    /// Which of two map images (0 or 1, equal global scores) the shortlist keeps for query `q`.
    fn first_of_two(
        a: MapImage,
        b: MapImage,
        q: &Features,
        q_points: &[Option<Vector3<f64>>],
    ) -> usize {
        let images = vec![a, b];
        let hits: Vec<Hit> = (0..2).map(|id| Hit { id, score: 0.5 }).collect();
        let list = Shortlist::new(&images, 64);
        let kept = list
            .rerank(&images, q, q_points, &hits, 1, &Mnn::default(), 0.1)
            .unwrap();
        kept[0].id
    }

    #[test]
    fn geometric_consistency_outvotes_more_matches() {
        // The query's 30 keypoints on a 3D grid. Image 1 matches 20 of them at the same 3D
        // layout (moved rigidly); image 0 matches all 30, but at scrambled 3D positions.
        let q = features(descriptors(30, 7), vec![1.0; 30]);
        let q_points: Vec<Option<Vector3<f64>>> = (0..30)
            .map(|i| {
                let i = i as f64;
                Some(Vector3::new(
                    i % 5.0,
                    (i / 5.0).floor() * 0.7,
                    2.0 + i * 0.1,
                ))
            })
            .collect();
        let mut consistent = map_image(&q);
        let mut scrambled = map_image(&q);
        for i in 0..30 {
            let p = q_points[i].unwrap() + Vector3::new(0.3, -0.2, 1.0);
            consistent.points[i] = if i < 20 {
                p.cast::<f32>().into()
            } else {
                [f32::NAN; 3]
            };
            let s = q_points[(i * 7 + 3) % 30].unwrap();
            scrambled.points[i] = s
                .component_mul(&Vector3::new(1.0, 1.9, 0.6))
                .cast::<f32>()
                .into();
        }
        assert_eq!(
            first_of_two(scrambled, consistent, &q, &q_points),
            1,
            "20 consistent matches beat 30 scrambled ones"
        );
    }

    #[test]
    fn a_hub_agreeing_with_matches_that_disagree_does_not_outvote_a_rigid_set() {
        // Image 0 matches all 30 query keypoints: the first at the same place, every other at
        // its own distance from the first but in a scrambled direction, so each agrees with the
        // first (one star of 29) and hardly with one another. Image 1 matches only 12, moved
        // rigidly: 12 matches that all agree with one another.
        let q = features(descriptors(30, 11), vec![1.0; 30]);
        let centre = Vector3::new(0.0, 0.0, 3.0);
        let at = |radius: f64, angle: f64| {
            centre + radius * Vector3::new(angle.cos(), angle.sin(), 0.3 * (2.0 * angle).sin())
        };
        let q_points: Vec<Option<Vector3<f64>>> = (0..30)
            .map(|i| {
                Some(if i == 0 {
                    centre
                } else {
                    at(0.4 + 0.07 * i as f64, 0.9 * i as f64)
                })
            })
            .collect();
        let mut hub = map_image(&q);
        let mut rigid = map_image(&q);
        let moved = Vector3::new(0.5, 0.1, -0.4);
        for (i, qp) in q_points.iter().enumerate() {
            let qp = qp.unwrap();
            let p = if i == 0 {
                centre
            } else {
                let r = (qp - centre).norm();
                // The same distance from the first match, another direction.
                centre + r * (at(1.0, 0.9 * i as f64 + 2.1 * i as f64) - centre).normalize()
            };
            hub.points[i] = p.cast::<f32>().into();
            if i < 12 {
                let p = qp + moved;
                rigid.points[i] = p.cast::<f32>().into();
            }
        }
        // The premise: the hub's star is larger than the whole rigid set.
        let src: Vec<Vector3<f64>> = q_points.iter().map(|p| p.unwrap()).collect();
        let dst: Vec<Vector3<f64>> = hub.points.iter().map(|&p| crate::verify::vec3(p)).collect();
        let g = consistency_graph(&src, &dst, &[true; 30], 0.1);
        assert!(g.degree(0) >= 29, "the hub agrees with every other match");
        assert_eq!(
            first_of_two(hub, rigid, &q, &q_points),
            1,
            "12 mutually consistent matches beat a star of 29"
        );
    }

    #[test]
    fn the_last_vote_sees_keypoints_the_first_two_do_not() {
        // The query's 40 descriptors. The decoy holds 10 of them among its strongest; the right
        // image all 40, but as its keypoints 300 to 339, beyond the first two votes' 128 and 256.
        let q = features(descriptors(40, 21), vec![1.0; 40]);
        let descending = |n: usize| (0..n).map(|i| 1.0 - i as f32 / 1000.0).collect::<Vec<_>>();
        let decoy = {
            let mut d = q.descriptors[..10 * 64].to_vec();
            d.extend_from_slice(&descriptors(50, 22));
            features(d, descending(60))
        };
        let right = {
            let mut d = descriptors(300, 23);
            d.extend_from_slice(&q.descriptors);
            features(d, descending(340))
        };
        let stranger = features(descriptors(60, 24), descending(60));
        let images: Vec<MapImage> = [decoy, right, stranger].iter().map(map_image).collect();
        let hits: Vec<Hit> = (0..3).map(|id| Hit { id, score: 0.5 }).collect();
        let list = Shortlist::new(&images, FINAL_KEYPOINTS);
        let kept = list
            .rerank(&images, &q, &[], &hits, 1, &Mnn::default(), 0.1)
            .unwrap();
        assert_eq!(
            kept[0].id, 1,
            "40 matches among the weaker keypoints beat 10 strong ones"
        );
        let first_only = list
            .ranked_by_vote(
                &images,
                &q,
                &[],
                &hits,
                COARSE_KEYPOINTS,
                &Mnn::default(),
                0.1,
            )
            .unwrap();
        assert_eq!(
            first_only[0].id, 0,
            "the first vote alone sees only the decoy's"
        );
    }

    #[test]
    fn a_frame_without_keypoints_gets_no_votes_and_no_panic() {
        // ORB on a blank frame: no keypoints, descriptor length 0, against binary map images.
        let empty = Features {
            keypoints: Vec::new(),
            scores: Vec::new(),
            descriptors: Vec::new(),
            dim: 0,
            binary: Vec::new(),
            image_size: (256, 256),
        };
        let mut orb = map_image(&features(descriptors(4, 3), vec![1.0; 4]));
        orb.descriptors.clear();
        orb.dim = 0;
        orb.binary = vec![[7u8; 32]; 4];
        let images = vec![orb.clone(), orb];
        let hits: Vec<Hit> = (0..2).map(|id| Hit { id, score: 0.0 }).collect();
        let list = Shortlist::new(&images, 8);
        let kept = list
            .rerank(&images, &empty, &[], &hits, 1, &Mnn::default(), 0.1)
            .unwrap();
        assert_eq!(kept.len(), 1);
        assert_eq!(kept[0].id, 0, "no votes: the global order stands");
    }

    #[test]
    fn strongest_indices_are_best_first() {
        assert_eq!(strongest_indices(&[0.1, 0.9, 0.5, 0.9], 3), vec![1, 3, 2]);
        assert_eq!(strongest_indices(&[0.3], 4), vec![0]);
    }
}
