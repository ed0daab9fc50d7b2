//! Maximum clique of a consistency graph: exact branch and bound within a budget of search nodes
//! (and a wall-clock safety net), with a greedy lower bound and a k-core upper bound that settle most
//! graphs without any search.
//!
//! Why this shape: the consistency graph of correspondences is sparse when most matches are outliers
//! (the exact search is fast there) and nearly complete when most are inliers (the exact search on a
//! dense graph is exponential, the failure TEASER++ users report as > 30 s). The greedy clique grown in
//! core-number order finds the whole inlier set of a dense graph at once, and when it reaches the
//! k-core bound it is provably maximum, so no search runs. Otherwise a bitset branch and bound with
//! greedy-colouring bounds (Tomita/San Segundo style) searches until its node budget, and the result
//! says whether it is exact. The budget counts nodes, not time, so an answer does not depend on how
//! busy the machine is; the time limit only stops a search the node budget did not foresee (a
//! machine many times slower or overloaded).

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

    /// Add the edges {i, start + b} for every set bit b of `mask` (`i < start`, `start + 64 <= n`
    /// or the mask's bits past `n - start` clear): up to 64 edges of vertex `i` at once, as
    /// [`Graph::add_edge`] on each.
    pub fn add_edges_from(&mut self, i: usize, start: usize, mask: u64) {
        debug_assert!(i < start && (start + 64 <= self.n || mask >> (self.n - start) == 0));
        if mask == 0 {
            return;
        }
        let w = self.words;
        let (word, shift) = (start / 64, start % 64);
        let row = &mut self.adj[i * w..(i + 1) * w];
        row[word] |= mask << shift;
        if shift > 0 && word + 1 < w {
            row[word + 1] |= mask >> (64 - shift);
        }
        let (iw, ib) = (i / 64, 1u64 << (i % 64));
        let mut m = mask;
        while m != 0 {
            let j = start + m.trailing_zeros() as usize;
            m &= m - 1;
            self.adj[j * w + iw] |= ib;
        }
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

    /// The subgraph induced by `vertices` (ascending), vertex `i` of it being `vertices[i]`.
    pub fn induced(&self, vertices: &[usize]) -> Graph {
        debug_assert!(vertices.windows(2).all(|w| w[0] < w[1]));
        let mut index = vec![usize::MAX; self.n];
        for (i, &v) in vertices.iter().enumerate() {
            index[v] = i;
        }
        let mut sub = Graph::new(vertices.len());
        let w = sub.words;
        for (i, &v) in vertices.iter().enumerate() {
            let row = &mut sub.adj[i * w..(i + 1) * w];
            for u in bits_iter(self.row(v)) {
                if index[u] != usize::MAX {
                    bit_set(row, index[u]);
                }
            }
        }
        sub
    }

    /// Core number of every vertex: the largest `k` such that the vertex belongs to a subgraph in
    /// which every vertex has at least `k` neighbours. Batagelj and Zaversnik's O(edges) peeling
    /// (2003): vertices kept sorted by their current degree in one array with the start of each
    /// degree's bin, the lowest-degree vertex removed next, each neighbour of higher degree moved
    /// one bin down by a swap. No allocation beyond four arrays of `n` (a shortlist vote runs this
    /// on every candidate image).
    pub fn core_numbers(&self) -> Vec<usize> {
        let n = self.n;
        let mut deg: Vec<usize> = (0..n).map(|i| self.degree(i)).collect();
        let max_deg = deg.iter().copied().max().unwrap_or(0);
        // bin[d]: where the vertices of degree d start in `vert` (a counting sort by degree).
        let mut bin = vec![0usize; max_deg + 2];
        for &d in &deg {
            bin[d + 1] += 1;
        }
        for d in 1..bin.len() {
            bin[d] += bin[d - 1];
        }
        let mut vert = vec![0usize; n];
        let mut pos = vec![0usize; n];
        {
            let mut next = bin.clone();
            for (v, &d) in deg.iter().enumerate() {
                pos[v] = next[d];
                vert[next[d]] = v;
                next[d] += 1;
            }
        }
        for i in 0..n {
            let v = vert[i];
            // `deg[v]` is final: v's core number.
            for u in bits_iter(self.row(v)) {
                if deg[u] > deg[v] {
                    // Move u to the front of its bin, then shrink that bin past it.
                    let du = deg[u];
                    let (pu, pw) = (pos[u], bin[du]);
                    let w = vert[pw];
                    if u != w {
                        vert.swap(pu, pw);
                        pos[u] = pw;
                        pos[w] = pu;
                    }
                    bin[du] += 1;
                    deg[u] -= 1;
                }
            }
        }
        deg
    }
}

/// How much work a clique search may do: it stops at whichever limit comes first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Budget {
    /// Branch-and-bound nodes the exact search may visit: the limit that binds on any machine at
    /// rest, so the answer is reproducible.
    pub nodes: u64,
    /// Wall-clock safety net for the whole call (greedy phase and search), checked every 256 nodes.
    pub time: Duration,
}

impl Budget {
    /// Only a time limit (no node limit), as before node budgets.
    pub fn time(time: Duration) -> Self {
        Self {
            nodes: u64::MAX,
            time,
        }
    }
}

struct Search<'g> {
    g: &'g Graph,
    /// The largest clique the search found, once larger than `floor`.
    best: Vec<usize>,
    /// Size of the clique known before the search (the greedy one).
    floor: usize,
    start: Instant,
    budget: Budget,
    nodes: u64,
    aborted: bool,
    /// Per depth of the search: its candidate set and its colour order, reused from node to node
    /// (the search allocates only when it first reaches a depth).
    levels: Vec<(Bits, Vec<(usize, usize)>)>,
    /// The colouring's two working sets.
    uncoloured: Bits,
    class: Bits,
    /// The complement matching's buffers.
    matching: MatchingScratch,
}

/// Working buffers of [`complement_matching`], reused from node to node.
#[derive(Default)]
struct MatchingScratch {
    free: Bits,
    /// Each vertex of `p` (ascending) with its number of non-neighbours in `p`.
    keyed: Vec<(usize, usize)>,
    /// Counting sort's bucket starts, one per possible count.
    starts: Vec<usize>,
    /// The vertices by (non-neighbours, index).
    order: Vec<usize>,
}

/// The size of a matching of the non-edges among `p` (greedy, the vertices with the fewest
/// non-neighbours in `p` first, ties by index, which keeps it near the maximum).
fn complement_matching(g: &Graph, p: &[u64], s: &mut MatchingScratch) -> usize {
    let size = bit_count(p);
    s.keyed.clear();
    for v in bits_iter(p) {
        let joined: usize = p
            .iter()
            .zip(g.row(v))
            .map(|(a, b)| (a & b).count_ones() as usize)
            .sum();
        s.keyed.push((size - 1 - joined, v));
    }
    // Counting sort by the count, stable, so ties stay in index order: the order of sorting the
    // (count, index) pairs, in time linear in |p|.
    s.starts.clear();
    s.starts.resize(size + 1, 0);
    for &(k, _) in &s.keyed {
        s.starts[k + 1] += 1;
    }
    for i in 1..s.starts.len() {
        s.starts[i] += s.starts[i - 1];
    }
    s.order.clear();
    s.order.resize(size, 0);
    for &(k, v) in &s.keyed {
        s.order[s.starts[k]] = v;
        s.starts[k] += 1;
    }
    s.free.clear();
    s.free.extend_from_slice(p);
    let free = &mut s.free;
    let mut matched = 0;
    for &v in s.order.iter() {
        if free[v / 64] & (1 << (v % 64)) == 0 {
            continue;
        }
        let row = g.row(v);
        for w in 0..free.len() {
            let mut apart = free[w] & !row[w];
            if w == v / 64 {
                apart &= !(1 << (v % 64));
            }
            if apart != 0 {
                let u = w * 64 + apart.trailing_zeros() as usize;
                bit_clear(free, u);
                bit_clear(free, v);
                matched += 1;
                break;
            }
        }
    }
    matched
}

/// Greedy colouring of `p` into `out`: vertices in colour-class order with their colour (1-based).
/// `u` and `q` are working sets.
fn colour(g: &Graph, p: &[u64], u: &mut Bits, q: &mut Bits, out: &mut Vec<(usize, usize)>) {
    out.clear();
    u.clear();
    u.extend_from_slice(p);
    let mut k = 0;
    while u.iter().any(|&w| w != 0) {
        k += 1;
        q.clear();
        q.extend_from_slice(u);
        while let Some(v) = first_bit(q) {
            bit_clear(q, v);
            bit_clear(u, v);
            for (qw, aw) in q.iter_mut().zip(g.row(v)) {
                *qw &= !aw;
            }
            out.push((v, k));
        }
    }
}

impl Search<'_> {
    /// Branch on the candidate set held in `levels[depth].0`.
    fn expand(&mut self, clique: &mut Vec<usize>, depth: usize) {
        self.nodes += 1;
        if self.nodes > self.budget.nodes
            || (self.nodes % 256 == 0 && self.start.elapsed() > self.budget.time)
        {
            self.aborted = true;
        }
        if self.aborted {
            return;
        }
        if self.levels.len() <= depth + 1 {
            self.levels.resize_with(depth + 2, Default::default);
        }
        let (mut p, mut order) = std::mem::take(&mut self.levels[depth]);
        // No clique in `p` is larger than |p| minus a matching of the pairs of `p` that are not
        // joined (each such pair loses at least one vertex): nearly complete candidate sets, where
        // the colouring bound is weak, are settled here.
        let size = bit_count(&p);
        let matched = complement_matching(self.g, &p, &mut self.matching);
        if clique.len() + size - matched <= self.best.len().max(self.floor) {
            self.levels[depth] = (p, order);
            return;
        }
        colour(
            self.g,
            &p,
            &mut self.uncoloured,
            &mut self.class,
            &mut order,
        );
        for &(v, c) in order.iter().rev() {
            if clique.len() + c <= self.best.len().max(self.floor) || self.aborted {
                break;
            }
            clique.push(v);
            let np = &mut self.levels[depth + 1].0;
            np.clear();
            np.extend(p.iter().zip(self.g.row(v)).map(|(a, b)| a & b));
            if np.iter().all(|&w| w == 0) {
                if clique.len() > self.best.len().max(self.floor) {
                    self.best.clear();
                    self.best.extend_from_slice(clique);
                }
            } else {
                self.expand(clique, depth + 1);
            }
            clique.pop();
            bit_clear(&mut p, v);
        }
        self.levels[depth] = (p, order);
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
/// found so far, with `exact = false`). Within the node budget the answer is a function of `g`
/// alone.
pub fn max_clique(g: &Graph, budget: Budget) -> CliqueResult {
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
    by_degree.sort_unstable_by_key(|&v| (std::cmp::Reverse(degree[v]), v));
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
    by_core.sort_unstable_by_key(|&v| (std::cmp::Reverse(core[v]), v));
    for &v in by_core.iter().take(64) {
        // At most 64 greedy cliques, each O(n + k * words): bounded work, so no node count; the
        // clock only guards a machine far slower than the budget foresaw.
        if core[v] < best.len() || start.elapsed() > budget.time / 2 {
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
        // Only vertices with core number >= |best| can be in a larger clique: the search runs on
        // the subgraph they induce, numbered in their order (so it visits them as it would in `g`,
        // on shorter bitsets).
        let kept: Vec<usize> = (0..g.len()).filter(|&v| core[v] >= best.len()).collect();
        let sub = g.induced(&kept);
        let mut p: Bits = vec![0; sub.words];
        for v in 0..sub.len() {
            bit_set(&mut p, v);
        }
        let floor = best.len();
        let mut s = Search {
            g: &sub,
            best: Vec::new(),
            floor,
            start,
            budget,
            nodes: 0,
            aborted: false,
            levels: vec![(p, Vec::new())],
            uncoloured: Vec::with_capacity(g.words),
            class: Vec::with_capacity(g.words),
            matching: MatchingScratch::default(),
        };
        s.expand(&mut Vec::new(), 0);
        exact = !s.aborted;
        if s.best.len() > floor {
            best = s.best.iter().map(|&v| kept[v]).collect();
        }
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
    fn an_induced_subgraph_keeps_exactly_the_edges_among_its_vertices() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = 150;
        let mut g = Graph::new(n);
        for i in 0..n {
            for j in i + 1..n {
                if rng.gen_bool(0.3) {
                    g.add_edge(i, j);
                }
            }
        }
        let kept: Vec<usize> = (0..n).filter(|v| v % 3 != 1).collect();
        let sub = g.induced(&kept);
        assert_eq!(sub.len(), kept.len());
        for (a, &i) in kept.iter().enumerate() {
            for (b, &j) in kept.iter().enumerate() {
                assert_eq!(sub.has_edge(a, b), a != b && g.has_edge(i, j), "{i} {j}");
            }
        }
    }

    #[test]
    fn a_planted_clique_is_found_where_the_bounds_need_the_search() {
        // A dense random block of 80 vertices (core numbers near 40, cliques near 10) holding a
        // planted clique of 14, among 180 sparse vertices the search leaves out by their core
        // number: the greedy clique falls short of the core bound, so the exact search runs.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for trial in 0..5 {
            let n = 260;
            let block = |v: usize| v % 13 < 4;
            let planted: Vec<usize> = (0..n)
                .filter(|&v| block(v))
                .skip(trial)
                .step_by(5)
                .take(14)
                .collect();
            let mut g = Graph::new(n);
            for i in 0..n {
                for j in i + 1..n {
                    let p = if block(i) && block(j) { 0.5 } else { 0.02 };
                    if (planted.contains(&i) && planted.contains(&j)) || rng.gen_bool(p) {
                        g.add_edge(i, j);
                    }
                }
            }
            let core = g.core_numbers();
            assert!(
                core.iter().filter(|&&c| c < 14).count() > 100,
                "trial {trial}"
            );
            let r = max_clique(&g, Budget::time(Duration::from_secs(10)));
            assert!(
                r.exact && r.vertices.len() >= 14,
                "trial {trial}: {}",
                r.vertices.len()
            );
            for (a, &i) in r.vertices.iter().enumerate() {
                assert!(r.vertices[a + 1..].iter().all(|&j| g.has_edge(i, j)));
            }
        }
    }

    #[test]
    fn a_node_budget_gives_the_same_clique_whatever_the_clock() {
        // A graph the exact search cannot settle in 50 nodes (dense random, G(120, 0.6)): cut by
        // nodes, the answer is the same with a generous clock, a tight one that the node limit
        // still meets first, and from a thread competing with three busy ones; with enough nodes
        // it is exact, and no smaller.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = 120;
        let mut g = Graph::new(n);
        for i in 0..n {
            for j in i + 1..n {
                if rng.gen_bool(0.6) {
                    g.add_edge(i, j);
                }
            }
        }
        let cut = |time| max_clique(&g, Budget { nodes: 50, time });
        let first = cut(Duration::from_secs(3600));
        assert!(!first.exact, "50 nodes settled it: pick a harder graph");
        assert_eq!(cut(Duration::from_secs(1)), first);
        let stop = std::sync::atomic::AtomicBool::new(false);
        std::thread::scope(|scope| {
            for _ in 0..3 {
                scope.spawn(|| {
                    let mut x = 0u64;
                    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                        x = std::hint::black_box(
                            x.wrapping_mul(6364136223846793005).wrapping_add(1),
                        );
                    }
                });
            }
            for _ in 0..5 {
                assert_eq!(cut(Duration::from_secs(3600)), first);
            }
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
        });
        let full = max_clique(&g, Budget::time(Duration::from_secs(60)));
        assert!(full.exact && full.vertices.len() >= first.vertices.len());
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
            let r = max_clique(&g, Budget::time(Duration::from_secs(5)));
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
        let r = max_clique(&g, Budget::time(Duration::from_millis(50)));
        assert!(
            r.vertices.len() >= n - missing.len(),
            "{}",
            r.vertices.len()
        );
        // The budget bounds the work even when the bound is not met exactly.
        assert!(t.elapsed() < Duration::from_secs(5));
    }

    /// Core numbers by repeated deletion of the vertices under each `k` (the definition).
    fn core_numbers_by_definition(g: &Graph) -> Vec<usize> {
        let n = g.len();
        let mut core = vec![0; n];
        for k in 1..n {
            let mut alive = vec![true; n];
            loop {
                let drop: Vec<usize> = (0..n)
                    .filter(|&v| {
                        alive[v] && (0..n).filter(|&u| alive[u] && g.has_edge(v, u)).count() < k
                    })
                    .collect();
                if drop.is_empty() {
                    break;
                }
                for v in drop {
                    alive[v] = false;
                }
            }
            for v in (0..n).filter(|&v| alive[v]) {
                core[v] = k;
            }
        }
        core
    }

    #[test]
    fn edges_added_by_mask_are_those_added_one_by_one() {
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for n in [2usize, 63, 64, 65, 130, 200] {
            let (mut by_mask, mut one_by_one) = (Graph::new(n), Graph::new(n));
            for i in 0..n - 1 {
                for start in (i + 1..n).step_by(64) {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    let len = (n - start).min(64);
                    let mask = if len == 64 {
                        x
                    } else {
                        x & ((1u64 << len) - 1)
                    };
                    by_mask.add_edges_from(i, start, mask);
                    for b in (0..len).filter(|&b| mask >> b & 1 == 1) {
                        one_by_one.add_edge(i, start + b);
                    }
                }
            }
            assert_eq!(by_mask.adj, one_by_one.adj, "n {n}");
        }
    }

    #[test]
    fn core_numbers_match_the_definition_on_random_graphs() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for trial in 0..60 {
            let n = 1 + trial % 70;
            let density = [0.05, 0.2, 0.5, 0.9][trial % 4];
            let mut g = Graph::new(n);
            for i in 0..n {
                for j in i + 1..n {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    if (x >> 11) as f64 / (1u64 << 53) as f64 <= density {
                        g.add_edge(i, j);
                    }
                }
            }
            assert_eq!(g.core_numbers(), core_numbers_by_definition(&g), "n {n}");
        }
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
            max_clique(&g, Budget::time(Duration::from_secs(1))).vertices,
            vec![0, 1, 2]
        );
    }
}
