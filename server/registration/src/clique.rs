//! Maximum clique of a consistency graph: exact branch and bound within a time budget, with a greedy
//! lower bound and a k-core upper bound that settle most graphs without any search.
//!
//! Why this shape: the consistency graph of correspondences is sparse when most matches are outliers
//! (the exact search is fast there) and nearly complete when most are inliers (the exact search on a
//! dense graph is exponential, the failure TEASER++ users report as > 30 s). The greedy clique grown in
//! core-number order finds the whole inlier set of a dense graph at once, and when it reaches the
//! k-core bound it is provably maximum, so no search runs. Otherwise a bitset branch and bound with
//! greedy-colouring bounds (Tomita/San Segundo style) searches until the time budget, and the result
//! says whether it is exact.

use std::time::{Duration, Instant};

/// An undirected graph on `n` vertices as adjacency bitsets.
#[derive(Debug, Clone)]
pub struct Graph {
    n: usize,
    words: usize,
    adj: Vec<u64>,
}

/// A clique and whether it is proven maximum.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CliqueResult {
    /// Vertices of the clique, sorted.
    pub vertices: Vec<usize>,
    /// True when the search proved no larger clique exists.
    pub exact: bool,
}

type Bits = Vec<u64>;

fn bit_set(b: &mut [u64], i: usize) {
    b[i / 64] |= 1 << (i % 64);
}

fn bit_clear(b: &mut [u64], i: usize) {
    b[i / 64] &= !(1 << (i % 64));
}

fn bit_count(b: &[u64]) -> usize {
    b.iter().map(|w| w.count_ones() as usize).sum()
}

fn first_bit(b: &[u64]) -> Option<usize> {
    b.iter()
        .enumerate()
        .find(|(_, w)| **w != 0)
        .map(|(i, w)| i * 64 + w.trailing_zeros() as usize)
}

fn bits_iter(b: &[u64]) -> impl Iterator<Item = usize> + '_ {
    b.iter().enumerate().flat_map(|(wi, &w)| {
        let mut w = w;
        std::iter::from_fn(move || {
            if w == 0 {
                return None;
            }
            let t = w.trailing_zeros() as usize;
            w &= w - 1;
            Some(wi * 64 + t)
        })
    })
}

impl Graph {
    /// A graph with `n` vertices and no edges.
    pub fn new(n: usize) -> Self {
        let words = n.div_ceil(64).max(1);
        Self {
            n,
            words,
            adj: vec![0; n * words],
        }
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.n
    }

    /// True when the graph has no vertices.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Add the edge {i, j} (i != j).
    pub fn add_edge(&mut self, i: usize, j: usize) {
        debug_assert!(i != j && i < self.n && j < self.n);
        let w = self.words;
        bit_set(&mut self.adj[i * w..(i + 1) * w], j);
        bit_set(&mut self.adj[j * w..(j + 1) * w], i);
    }

    /// Whether {i, j} is an edge.
    pub fn has_edge(&self, i: usize, j: usize) -> bool {
        self.row(i)[j / 64] & (1 << (j % 64)) != 0
    }

    fn row(&self, i: usize) -> &[u64] {
        &self.adj[i * self.words..(i + 1) * self.words]
    }

    /// Degree of vertex `i`.
    pub fn degree(&self, i: usize) -> usize {
        bit_count(self.row(i))
    }

    /// Core number of every vertex (Batagelj-Zaversnik peeling).
    pub fn core_numbers(&self) -> Vec<usize> {
        let n = self.n;
        let mut deg: Vec<usize> = (0..n).map(|i| self.degree(i)).collect();
        let max_deg = deg.iter().copied().max().unwrap_or(0);
        let mut bins: Vec<Vec<usize>> = vec![Vec::new(); max_deg + 1];
        for (v, &d) in deg.iter().enumerate() {
            bins[d].push(v);
        }
        let mut removed = vec![false; n];
        let mut core = vec![0; n];
        let mut k = 0;
        let mut left = n;
        while left > 0 {
            // Lowest non-empty bin at or above k; stale entries (degree changed) are skipped.
            let mut d = 0;
            let v = loop {
                if let Some(v) = bins[d].pop() {
                    if !removed[v] && deg[v] == d {
                        break v;
                    }
                } else {
                    d += 1;
                }
            };
            k = k.max(d);
            core[v] = k;
            removed[v] = true;
            left -= 1;
            for u in bits_iter(self.row(v)) {
                if !removed[u] && deg[u] > 0 {
                    deg[u] -= 1;
                    bins[deg[u]].push(u);
                }
            }
        }
        core
    }
}

struct Search<'g> {
    g: &'g Graph,
    best: Vec<usize>,
    start: Instant,
    budget: Duration,
    nodes: u64,
    aborted: bool,
}

impl Search<'_> {
    /// Greedy colouring of `p`: vertices in colour-class order with their colour (1-based).
    fn colour(&self, p: &Bits) -> Vec<(usize, usize)> {
        let mut out = Vec::with_capacity(bit_count(p));
        let mut u = p.clone();
        let mut k = 0;
        while u.iter().any(|&w| w != 0) {
            k += 1;
            let mut q = u.clone();
            while let Some(v) = first_bit(&q) {
                bit_clear(&mut q, v);
                bit_clear(&mut u, v);
                for (qw, aw) in q.iter_mut().zip(self.g.row(v)) {
                    *qw &= !aw;
                }
                out.push((v, k));
            }
        }
        out
    }

    fn expand(&mut self, clique: &mut Vec<usize>, mut p: Bits) {
        self.nodes += 1;
        if self.nodes % 256 == 0 && self.start.elapsed() > self.budget {
            self.aborted = true;
        }
        if self.aborted {
            return;
        }
        let order = self.colour(&p);
        for &(v, c) in order.iter().rev() {
            if clique.len() + c <= self.best.len() || self.aborted {
                return;
            }
            clique.push(v);
            let np: Bits = p.iter().zip(self.g.row(v)).map(|(a, b)| a & b).collect();
            if np.iter().all(|&w| w == 0) {
                if clique.len() > self.best.len() {
                    self.best = clique.clone();
                }
            } else {
                self.expand(clique, np);
            }
            clique.pop();
            bit_clear(&mut p, v);
        }
    }
}

/// Greedy clique from `seed`: walk the vertices in descending core order and keep each one adjacent to
/// everything kept so far. O(n + k n / 64) per call, cheap enough to try many seeds on large graphs.
fn greedy_from(g: &Graph, seed: usize, by_core: &[usize]) -> Vec<usize> {
    let mut clique = vec![seed];
    let mut cand: Bits = g.row(seed).to_vec();
    for &u in by_core {
        if cand[u / 64] & (1 << (u % 64)) != 0 {
            clique.push(u);
            for (c, a) in cand.iter_mut().zip(g.row(u)) {
                *c &= a;
            }
            if cand.iter().all(|&w| w == 0) {
                break;
            }
        }
    }
    clique
}

/// A maximum clique of `g`, exact unless the search would exceed `budget` (then the largest clique
/// found so far, with `exact = false`).
pub fn max_clique(g: &Graph, budget: Duration) -> CliqueResult {
    let start = Instant::now();
    if g.is_empty() {
        return CliqueResult {
            vertices: Vec::new(),
            exact: true,
        };
    }
    // Cheap bounds first: a greedy clique in degree order against the degree bound settles complete
    // and nearly complete graphs without the O(m) core decomposition.
    let degree: Vec<usize> = (0..g.len()).map(|v| g.degree(v)).collect();
    let mut by_degree: Vec<usize> = (0..g.len()).collect();
    by_degree.sort_by_key(|&v| (std::cmp::Reverse(degree[v]), v));
    let mut best = greedy_from(g, by_degree[0], &by_degree);
    if best.len() == degree[by_degree[0]] + 1 {
        best.sort_unstable();
        return CliqueResult {
            vertices: best,
            exact: true,
        };
    }
    let core = g.core_numbers();
    let upper = core.iter().copied().max().unwrap_or(0) + 1;
    // Greedy lower bound from the highest-core vertices.
    let mut by_core: Vec<usize> = (0..g.len()).collect();
    by_core.sort_by_key(|&v| (std::cmp::Reverse(core[v]), v));
    for &v in by_core.iter().take(64) {
        if core[v] < best.len() || start.elapsed() > budget / 2 {
            break;
        }
        let c = greedy_from(g, v, &by_core);
        if c.len() > best.len() {
            best = c;
        }
        if best.len() == upper {
            break;
        }
    }
    let mut exact = best.len() == upper;
    if !exact {
        // Only vertices with core number >= |best| can be in a larger clique.
        let mut p: Bits = vec![0; g.words];
        for (v, &c) in core.iter().enumerate() {
            if c >= best.len() {
                bit_set(&mut p, v);
            }
        }
        let mut s = Search {
            g,
            best,
            start,
            budget,
            nodes: 0,
            aborted: false,
        };
        s.expand(&mut Vec::new(), p);
        exact = !s.aborted;
        best = s.best;
    }
    best.sort_unstable();
    CliqueResult {
        vertices: best,
        exact,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn brute_force(g: &Graph) -> usize {
        let n = g.len();
        let mut best = 0;
        for mask in 0u32..(1 << n) {
            let vs: Vec<usize> = (0..n).filter(|i| mask & (1 << i) != 0).collect();
            let ok = vs
                .iter()
                .enumerate()
                .all(|(a, &i)| vs[a + 1..].iter().all(|&j| g.has_edge(i, j)));
            if ok {
                best = best.max(vs.len());
            }
        }
        best
    }

    #[test]
    fn matches_brute_force_on_random_graphs() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for trial in 0..60 {
            let n = rng.gen_range(1..15);
            let p = rng.gen_range(0.1..0.9);
            let mut g = Graph::new(n);
            for i in 0..n {
                for j in i + 1..n {
                    if rng.gen_bool(p) {
                        g.add_edge(i, j);
                    }
                }
            }
            let r = max_clique(&g, Duration::from_secs(5));
            assert!(r.exact);
            assert_eq!(r.vertices.len(), brute_force(&g), "trial {trial}");
            for (a, &i) in r.vertices.iter().enumerate() {
                for &j in &r.vertices[a + 1..] {
                    assert!(g.has_edge(i, j));
                }
            }
        }
    }

    #[test]
    fn dense_graph_is_settled_without_search() {
        // All inliers with a few pairs pushed past the bound by noise: nearly complete.
        let n = 3000;
        let missing: std::collections::HashSet<(usize, usize)> = (0..20)
            .map(|k| (k * 37 % n, (k * 37 + 1 + k * 101) % n))
            .map(|(a, b)| (a.min(b), a.max(b)))
            .collect();
        let mut g = Graph::new(n);
        for i in 0..n {
            for j in i + 1..n {
                if !missing.contains(&(i, j)) {
                    g.add_edge(i, j);
                }
            }
        }
        let t = Instant::now();
        let r = max_clique(&g, Duration::from_millis(50));
        assert!(
            r.vertices.len() >= n - missing.len(),
            "{}",
            r.vertices.len()
        );
        // The budget bounds the work even when the bound is not met exactly.
        assert!(t.elapsed() < Duration::from_secs(5));
    }

    #[test]
    fn core_numbers_of_a_known_graph() {
        // A triangle with a pendant vertex.
        let mut g = Graph::new(4);
        g.add_edge(0, 1);
        g.add_edge(1, 2);
        g.add_edge(0, 2);
        g.add_edge(2, 3);
        assert_eq!(g.core_numbers(), vec![2, 2, 2, 1]);
        assert_eq!(
            max_clique(&g, Duration::from_secs(1)).vertices,
            vec![0, 1, 2]
        );
    }
}
