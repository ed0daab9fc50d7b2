//! Bag of binary words: the classical retrieval baseline of the HPointLoc paper (DBoW2 over ORB).
//!
//! A vocabulary tree is learned on the map's own ORB descriptors by hierarchical k-majority (k-means
//! in Hamming space, where the centre of a cluster is the bitwise majority of its members), `branching`
//! children per node and `depth` levels, so a descriptor finds its word with `branching * depth`
//! Hamming distances. Images become TF-IDF vectors (term frequency times log(N / images containing the
//! word), L1-normalised) and are compared with DBoW2's L1 score `1 - |a - b|_1 / 2`, which for
//! non-negative L1-normalised vectors is the sum over shared words of `min(a_w, b_w)`: an inverted file
//! (word -> images holding it) visits only images that share a word with the query.

use rand::seq::SliceRandom;
use rand::SeedableRng;

use crate::index::Hit;
use crate::RetrievalError;

/// A 256-bit binary descriptor (ORB).
pub type Binary = [u8; 32];

fn hamming(a: &Binary, b: &Binary) -> u32 {
    a.chunks_exact(8)
        .zip(b.chunks_exact(8))
        .map(|(x, y)| {
            let x = u64::from_le_bytes(x.try_into().expect("8 bytes"));
            let y = u64::from_le_bytes(y.try_into().expect("8 bytes"));
            (x ^ y).count_ones()
        })
        .sum()
}

/// Vocabulary shape.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BowParams {
    /// Children per node. Default 10 (DBoW2's).
    pub branching: usize,
    /// Levels. Default 3 (at most 1000 words: enough for maps of thousands of images).
    pub depth: usize,
    /// k-majority iterations per node. Default 8.
    pub iterations: usize,
    /// Seed of the initial centres.
    pub seed: u64,
}

impl Default for BowParams {
    fn default() -> Self {
        Self {
            branching: 10,
            depth: 3,
            iterations: 8,
            seed: 1,
        }
    }
}

/// A node of the vocabulary tree: its centre, and either children or a word id.
#[derive(Debug, Clone, PartialEq)]
struct Node {
    centre: Binary,
    children: Vec<u32>,
    word: u32,
}

/// A learned vocabulary tree with the IDF weight of every word.
#[derive(Debug, Clone, PartialEq)]
pub struct Vocabulary {
    nodes: Vec<Node>,
    /// IDF weight per word.
    pub idf: Vec<f32>,
    /// The shape it was learned with.
    pub params: BowParams,
}

fn majority(members: &[&Binary]) -> Binary {
    let mut counts = [0u32; 256];
    for d in members {
        for (byte, &v) in d.iter().enumerate() {
            for bit in 0..8 {
                counts[byte * 8 + bit] += ((v >> bit) & 1) as u32;
            }
        }
    }
    let mut out = [0u8; 32];
    let half = members.len() as u32;
    for (i, &c) in counts.iter().enumerate() {
        if 2 * c > half {
            out[i / 8] |= 1 << (i % 8);
        }
    }
    out
}

/// Split `members` into at most `k` clusters by k-majority; returns (centre, members) per cluster.
fn k_majority<'a>(
    members: &[&'a Binary],
    k: usize,
    iterations: usize,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Vec<(Binary, Vec<&'a Binary>)> {
    // Distinct initial centres, chosen at random.
    let mut pool: Vec<&Binary> = members.to_vec();
    pool.shuffle(rng);
    let mut centres: Vec<Binary> = Vec::with_capacity(k);
    for d in pool {
        if centres.len() == k {
            break;
        }
        if !centres.contains(d) {
            centres.push(*d);
        }
    }
    let mut clusters: Vec<Vec<&Binary>> = Vec::new();
    for _ in 0..iterations.max(1) {
        clusters = vec![Vec::new(); centres.len()];
        for &d in members {
            let c = (0..centres.len())
                .min_by_key(|&c| hamming(&centres[c], d))
                .expect("at least one centre");
            clusters[c].push(d);
        }
        let next: Vec<Binary> = clusters
            .iter()
            .zip(&centres)
            .map(|(m, c)| if m.is_empty() { *c } else { majority(m) })
            .collect();
        if next == centres {
            break;
        }
        centres = next;
    }
    centres
        .into_iter()
        .zip(clusters)
        .filter(|(_, m)| !m.is_empty())
        .collect()
}

impl Vocabulary {
    /// Learn a vocabulary from the ORB descriptors of the map's images (one slice per image); the
    /// IDF weights count the images that contain each word.
    pub fn train(images: &[Vec<Binary>], params: BowParams) -> Result<Self, RetrievalError> {
        if params.branching < 2 || params.depth == 0 {
            return Err(RetrievalError::Input(format!(
                "a vocabulary needs branching >= 2 and depth >= 1 (got {} and {})",
                params.branching, params.depth
            )));
        }
        let all: Vec<&Binary> = images.iter().flatten().collect();
        if all.len() < params.branching {
            return Err(RetrievalError::Input(format!(
                "{} binary descriptors cannot train a vocabulary with branching {}",
                all.len(),
                params.branching
            )));
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(params.seed);
        let mut nodes = vec![Node {
            centre: [0; 32],
            children: Vec::new(),
            word: u32::MAX,
        }];
        // Breadth-first: (node id, level, members).
        let mut queue = std::collections::VecDeque::from([(0usize, 0usize, all)]);
        let mut words = 0u32;
        while let Some((id, level, members)) = queue.pop_front() {
            if level == params.depth || members.len() <= params.branching {
                nodes[id].word = words;
                words += 1;
                continue;
            }
            for (centre, m) in k_majority(&members, params.branching, params.iterations, &mut rng) {
                let child = nodes.len();
                nodes.push(Node {
                    centre,
                    children: Vec::new(),
                    word: u32::MAX,
                });
                nodes[id].children.push(child as u32);
                queue.push_back((child, level + 1, m));
            }
        }
        let mut voc = Self {
            nodes,
            idf: vec![0.0; words as usize],
            params,
        };
        voc.compute_idf(images);
        Ok(voc)
    }

    /// Set the IDF weights from the images of the map (`ln(N / images containing the word)`).
    pub fn compute_idf(&mut self, images: &[Vec<Binary>]) {
        let mut df = vec![0u32; self.idf.len()];
        for img in images {
            let mut seen: Vec<u32> = img.iter().map(|d| self.word(d)).collect();
            seen.sort_unstable();
            seen.dedup();
            for w in seen {
                df[w as usize] += 1;
            }
        }
        let n = images.len() as f32;
        self.idf = df
            .iter()
            .map(|&c| if c == 0 { 0.0 } else { (n / c as f32).ln() })
            .collect();
    }

    /// Number of words.
    pub fn words(&self) -> usize {
        self.idf.len()
    }

    /// The word of one descriptor: descend the tree to the nearest child at each level.
    pub fn word(&self, d: &Binary) -> u32 {
        let mut id = 0usize;
        loop {
            let node = &self.nodes[id];
            if node.children.is_empty() {
                return node.word;
            }
            id = *node
                .children
                .iter()
                .min_by_key(|&&c| hamming(&self.nodes[c as usize].centre, d))
                .expect("an inner node has children") as usize;
        }
    }

    /// The L1-normalised TF-IDF vector of one image, as (word, weight) sorted by word.
    pub fn bow(&self, descriptors: &[Binary]) -> Vec<(u32, f32)> {
        let mut words: Vec<u32> = descriptors.iter().map(|d| self.word(d)).collect();
        words.sort_unstable();
        let mut v: Vec<(u32, f32)> = Vec::new();
        for w in words {
            match v.last_mut() {
                Some((last, c)) if *last == w => *c += 1.0,
                _ => v.push((w, 1.0)),
            }
        }
        let n = descriptors.len().max(1) as f32;
        for (w, c) in &mut v {
            *c = *c / n * self.idf[*w as usize];
        }
        v.retain(|&(_, x)| x > 0.0);
        let sum: f32 = v.iter().map(|&(_, x)| x).sum();
        if sum > 0.0 {
            v.iter_mut().for_each(|(_, x)| *x /= sum);
        }
        v
    }

    /// Serialise (little-endian): params, node count, nodes (centre, word, child count, children), IDF.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut b = Vec::new();
        let p = &self.params;
        for v in [p.branching, p.depth, p.iterations] {
            b.extend_from_slice(&(v as u32).to_le_bytes());
        }
        b.extend_from_slice(&p.seed.to_le_bytes());
        b.extend_from_slice(&(self.nodes.len() as u32).to_le_bytes());
        for n in &self.nodes {
            b.extend_from_slice(&n.centre);
            b.extend_from_slice(&n.word.to_le_bytes());
            b.extend_from_slice(&(n.children.len() as u32).to_le_bytes());
            for c in &n.children {
                b.extend_from_slice(&c.to_le_bytes());
            }
        }
        b.extend_from_slice(&(self.idf.len() as u32).to_le_bytes());
        for x in &self.idf {
            b.extend_from_slice(&x.to_le_bytes());
        }
        b
    }

    /// Read what [`Vocabulary::to_bytes`] wrote, checking every count and reference.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, RetrievalError> {
        let mut r = pntr_core::bytes::Reader::new(bytes, "BoW vocabulary");
        let branching = r.u32()? as usize;
        let depth = r.u32()? as usize;
        let iterations = r.u32()? as usize;
        let seed = r.u64()?;
        let n = r.u32()? as usize;
        let mut nodes = Vec::with_capacity(n.min(bytes.len() / 40));
        for _ in 0..n {
            let centre: Binary = r.take(32)?.try_into().expect("32 bytes");
            let word = r.u32()?;
            let nc = r.u32()? as usize;
            let children = (0..nc).map(|_| r.u32()).collect::<Result<Vec<_>, _>>()?;
            nodes.push(Node {
                centre,
                children,
                word,
            });
        }
        let words = r.u32()? as usize;
        let idf = (0..words).map(|_| r.f32()).collect::<Result<Vec<_>, _>>()?;
        r.finish()?;
        let bad = |m: String| RetrievalError::Input(format!("BoW vocabulary: {m}"));
        if nodes.is_empty() {
            return Err(bad("no nodes".into()));
        }
        // Children point forward only (breadth-first order), so descending always terminates.
        for (i, node) in nodes.iter().enumerate() {
            if node.children.is_empty() && node.word as usize >= words {
                return Err(bad(format!("leaf {i} has word {} of {words}", node.word)));
            }
            if node
                .children
                .iter()
                .any(|&c| c as usize <= i || c as usize >= nodes.len())
            {
                return Err(bad(format!("node {i} has an invalid child")));
            }
        }
        Ok(Self {
            nodes,
            idf,
            params: BowParams {
                branching,
                depth,
                iterations,
                seed,
            },
        })
    }
}

/// DBoW2's L1 similarity of two L1-normalised BoW vectors (sorted by word): 1 for identical word
/// distributions, 0 for none in common.
pub fn l1_score(a: &[(u32, f32)], b: &[(u32, f32)]) -> f32 {
    let (mut i, mut j, mut s) = (0, 0, 0.0);
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                s += a[i].1.min(b[j].1);
                i += 1;
                j += 1;
            }
        }
    }
    s
}

/// An inverted file over the map's BoW vectors: word -> (image id, weight).
#[derive(Debug, Clone, PartialEq)]
pub struct InvertedFile {
    lists: Vec<Vec<(u32, f32)>>,
    images: usize,
}

impl InvertedFile {
    /// Index the BoW vectors of the map's images (ids are their order).
    pub fn build(words: usize, vectors: &[Vec<(u32, f32)>]) -> Result<Self, RetrievalError> {
        let mut lists = vec![Vec::new(); words];
        for (id, v) in vectors.iter().enumerate() {
            for &(w, x) in v {
                lists
                    .get_mut(w as usize)
                    .ok_or_else(|| {
                        RetrievalError::Input(format!("word {w} outside a {words}-word vocabulary"))
                    })?
                    .push((id as u32, x));
            }
        }
        Ok(Self {
            lists,
            images: vectors.len(),
        })
    }

    /// Number of indexed images.
    pub fn len(&self) -> usize {
        self.images
    }

    /// True when no image is indexed.
    pub fn is_empty(&self) -> bool {
        self.images == 0
    }

    /// The `k` images with the highest L1 score against `query`, best first (ties by id).
    pub fn search(&self, query: &[(u32, f32)], k: usize) -> Vec<Hit> {
        let mut score = vec![0f32; self.images];
        for &(w, q) in query {
            if let Some(list) = self.lists.get(w as usize) {
                for &(id, x) in list {
                    score[id as usize] += q.min(x);
                }
            }
        }
        let mut hits: Vec<Hit> = score
            .into_iter()
            .enumerate()
            .map(|(id, score)| Hit { id, score })
            .collect();
        let k = k.min(hits.len());
        if k == 0 {
            return Vec::new();
        }
        let order = |a: &Hit, b: &Hit| b.score.total_cmp(&a.score).then(a.id.cmp(&b.id));
        hits.select_nth_unstable_by(k - 1, order);
        hits.truncate(k);
        hits.sort_by(order);
        hits
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    fn noisy(base: &Binary, flips: usize, rng: &mut rand_chacha::ChaCha8Rng) -> Binary {
        let mut d = *base;
        for _ in 0..flips {
            let bit = rng.gen_range(0..256);
            d[bit / 8] ^= 1 << (bit % 8);
        }
        d
    }

    #[test]
    fn images_sharing_patterns_score_highest_and_the_inverted_file_agrees_with_direct_scoring() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        // 40 "patterns"; image i shows patterns 4i..4i+8 (neighbours overlap) with bit noise.
        let patterns: Vec<Binary> = (0..48).map(|_| rng.gen()).collect();
        let image = |i: usize, rng: &mut rand_chacha::ChaCha8Rng| -> Vec<Binary> {
            (0..80)
                .map(|j| noisy(&patterns[4 * i + j % 8], 10, rng))
                .collect()
        };
        let db: Vec<Vec<Binary>> = (0..10).map(|i| image(i, &mut rng)).collect();
        let voc = Vocabulary::train(&db, BowParams::default()).unwrap();
        assert!(voc.words() > 40, "{} words", voc.words());
        let vecs: Vec<Vec<(u32, f32)>> = db.iter().map(|d| voc.bow(d)).collect();
        let inv = InvertedFile::build(voc.words(), &vecs).unwrap();
        for i in 0..10 {
            let q = voc.bow(&image(i, &mut rng));
            let hits = inv.search(&q, 3);
            assert_eq!(hits[0].id, i, "query {i}: {hits:?}");
            for h in &hits {
                assert!((h.score - l1_score(&q, &vecs[h.id])).abs() < 1e-5);
            }
        }
        assert!((l1_score(&vecs[0], &vecs[0]) - 1.0).abs() < 1e-5);
        let back = Vocabulary::from_bytes(&voc.to_bytes()).unwrap();
        assert_eq!(back, voc);
        let bytes = voc.to_bytes();
        assert!(Vocabulary::from_bytes(&bytes[..bytes.len() - 3]).is_err());
    }

    #[test]
    fn too_few_descriptors_are_refused() {
        assert!(Vocabulary::train(&[vec![[0u8; 32]; 3]], BowParams::default()).is_err());
    }
}
