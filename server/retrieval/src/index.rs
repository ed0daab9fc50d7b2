//! The global-descriptor index: faiss with inner product on L2-normalised vectors.

use faiss::index::IndexImpl;
use faiss::{Index, MetricType};

use crate::RetrievalError;

/// Most map vectors an approximate index (IVF cells) is trained on.
pub const TRAINING_VECTORS: usize = 8192;

/// Most map vectors PCA-whitening is learned from. Fewer vectors than dimensions let faiss
/// decompose the Gram matrix of the sample instead of the 4096 x 4096 covariance: 18-23 s of
/// training instead of 160 s for VLAD, whatever the map's size; 3072 vectors ranked the right
/// Point as well (BENCHMARKS.md, "A deeper shortlist").
pub const PCA_TRAINING_VECTORS: usize = 2048;

/// From this many map images on, `auto` learns PCA-whitening to [`AUTO_PCA_DIM`] dimensions
/// instead of searching the raw descriptors exactly (for descriptors longer than that). Below it
/// exact search costs at most a few milliseconds and ranks the right place as well or better;
/// above it the reduced vectors are 8x cheaper to scan (a flat scan of 4096-d vectors is bound by
/// memory: 16 ms at 10,500 images) and, after the shortlist's vote, rank the right Point as well
/// (4,200 images) or slightly better (10,500) (BENCHMARKS.md, "A deeper shortlist").
pub const AUTO_PCA_FROM: usize = 4096;

/// Output dimension of `auto`'s PCA-whitening.
pub const AUTO_PCA_DIM: u32 = 512;

/// Which faiss index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IndexKind {
    /// Chosen by the map's size when the index is built ([`IndexKind::resolve`]): exact search
    /// below [`AUTO_PCA_FROM`] images, PCA-whitening to [`AUTO_PCA_DIM`] then exact search from
    /// there on. A built index records the kind it resolved to.
    Auto,
    /// Exact search (what `auto` chooses for small maps).
    Flat,
    /// HNSW graph with `m` links per node: approximate, for maps of 100k images and more.
    Hnsw {
        /// Links per node.
        m: u32,
    },
    /// Inverted file with `nlist` cells probed `nprobe` at a time: approximate, trained on the map.
    Ivf {
        /// Number of cells (k-means centroids).
        nlist: u32,
        /// Cells visited per query.
        nprobe: u32,
    },
    /// PCA-whitening to `dim` dimensions learned on the map, re-normalised, then exact search.
    PcaWhiten {
        /// Output dimension (at most the number of map vectors).
        dim: u32,
    },
}

impl IndexKind {
    /// Parse a name: `auto`, `flat`, `hnsw<M>` (e.g. hnsw32), `ivf<NLIST>` (e.g. ivf1024, 16
    /// probes) or `pcaw<D>` (e.g. pcaw256).
    pub fn parse(name: &str) -> Result<Self, RetrievalError> {
        let num = |prefix: &str| -> Option<u32> {
            name.strip_prefix(prefix)?.parse().ok().filter(|&v| v > 0)
        };
        if name == "auto" {
            Ok(Self::Auto)
        } else if name == "flat" {
            Ok(Self::Flat)
        } else if let Some(m) = num("hnsw") {
            Ok(Self::Hnsw { m })
        } else if let Some(nlist) = num("ivf") {
            Ok(Self::Ivf { nlist, nprobe: 16 })
        } else if let Some(dim) = num("pcaw") {
            Ok(Self::PcaWhiten { dim })
        } else {
            Err(RetrievalError::Input(format!(
                "unknown index `{name}` (auto, flat, hnsw<M>, ivf<NLIST>, pcaw<DIM>)"
            )))
        }
    }

    /// The name [`IndexKind::parse`] reads.
    pub fn name(&self) -> String {
        match self {
            Self::Auto => "auto".into(),
            Self::Flat => "flat".into(),
            Self::Hnsw { m } => format!("hnsw{m}"),
            Self::Ivf { nlist, .. } => format!("ivf{nlist}"),
            Self::PcaWhiten { dim } => format!("pcaw{dim}"),
        }
    }
}

impl IndexKind {
    /// The concrete kind for `n` vectors of `dim` dimensions: `Auto` chooses (exact search below
    /// [`AUTO_PCA_FROM`] vectors or when `dim` is not above [`AUTO_PCA_DIM`], PCA-whitening to
    /// [`AUTO_PCA_DIM`] otherwise); any other kind is itself.
    pub fn resolve(self, n: usize, dim: usize) -> Self {
        match self {
            Self::Auto if n >= AUTO_PCA_FROM && dim > AUTO_PCA_DIM as usize => {
                Self::PcaWhiten { dim: AUTO_PCA_DIM }
            }
            Self::Auto => Self::Flat,
            other => other,
        }
    }
}

/// How deep [`GlobalIndex::search_among`] searches an index that cannot filter by id.
const SEARCH_AMONG_DEPTH: usize = 1024;

/// A searchable set of global descriptors; ids are insertion order.
pub struct GlobalIndex {
    index: IndexImpl,
    dim: usize,
    len: usize,
    /// Whether the index holds the vectors as they are searched (flat, HNSW over flat storage), so
    /// that [`GlobalIndex::search_among`] scores the allowed ids exactly from them.
    exact_among: bool,
}

/// The faiss file tags (`fourcc` in faiss's `index_write.cpp`) of the index types that store the
/// vectors unchanged and reconstruct them exactly: flat with inner product, L2 or another metric,
/// and HNSW over flat storage.
const EXACT_AMONG_TAGS: [&[u8; 4]; 4] = [b"IxFI", b"IxF2", b"IxFl", b"IHNf"];

impl std::fmt::Debug for GlobalIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GlobalIndex(dim {}, {} vectors)", self.dim, self.len)
    }
}

/// One search hit: database id and inner-product similarity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Database id (insertion order).
    pub id: usize,
    /// Similarity (cosine for normalised vectors).
    pub score: f32,
}

impl GlobalIndex {
    /// Build from `vectors` (`n * dim` values); `Auto` is resolved first ([`IndexKind::resolve`]).
    pub fn build(vectors: &[f32], dim: usize, kind: IndexKind) -> Result<Self, RetrievalError> {
        if dim == 0 || vectors.len() % dim != 0 {
            return Err(RetrievalError::Input(format!(
                "{} values are not {dim}-d vectors",
                vectors.len()
            )));
        }
        let n = vectors.len() / dim;
        let kind = kind.resolve(n, dim);
        let desc = match kind {
            // `Auto` resolved to one of the others above.
            IndexKind::Flat | IndexKind::Auto => "Flat".to_string(),
            IndexKind::Hnsw { m } => format!("HNSW{m},Flat"),
            IndexKind::Ivf { nlist, .. } => {
                if (nlist as usize) > n {
                    return Err(RetrievalError::Input(format!(
                        "ivf{nlist} needs at least {nlist} map vectors, the map has {n}"
                    )));
                }
                format!("IVF{nlist},Flat")
            }
            IndexKind::PcaWhiten { dim: d } => {
                if d as usize > n.min(dim) {
                    return Err(RetrievalError::Input(format!(
                        "pcaw{d} needs at least {d} map vectors of at least {d} dimensions ({n} of {dim})"
                    )));
                }
                format!("PCAW{d},L2norm,Flat")
            }
        };
        let mut index = faiss::index_factory(dim as u32, desc, MetricType::InnerProduct)?;
        if !index.is_trained() {
            // Training (k-means cells, PCA) on an even sample keeps the cost bounded for huge maps.
            let cap = match kind {
                IndexKind::PcaWhiten { dim: d } => PCA_TRAINING_VECTORS.max(d as usize),
                _ => TRAINING_VECTORS,
            };
            // Exactly min(n, cap) vectors, evenly spaced through the map.
            let take = n.min(cap);
            let sample: Vec<f32> = (0..take)
                .flat_map(|i| {
                    let v = i * n / take;
                    vectors[v * dim..(v + 1) * dim].iter().copied()
                })
                .collect();
            index.train(&sample)?;
        }
        index.add(vectors)?;
        if let IndexKind::Ivf { nprobe, .. } = kind {
            faiss::index::autotune::ParameterSpace::new()?
                .set_index_parameter(&index, "nprobe", nprobe)?;
        }
        Ok(Self {
            index,
            dim,
            len: vectors.len() / dim,
            exact_among: matches!(kind, IndexKind::Flat | IndexKind::Hnsw { .. }),
        })
    }

    /// Append `vectors` (`n * dim` values) to the trained index; their ids continue from
    /// [`GlobalIndex::len`].
    pub fn add(&mut self, vectors: &[f32]) -> Result<(), RetrievalError> {
        if vectors.len() % self.dim != 0 {
            return Err(RetrievalError::Input(format!(
                "{} values are not {}-d vectors",
                vectors.len(),
                self.dim
            )));
        }
        if vectors.is_empty() {
            return Ok(());
        }
        self.index.add(vectors)?;
        self.len += vectors.len() / self.dim;
        Ok(())
    }

    /// Serialise with faiss's own writer (through a temporary file: the crate has no in-memory writer).
    pub fn to_bytes(&self) -> Result<Vec<u8>, RetrievalError> {
        let dir = tempfile::tempdir().map_err(|e| RetrievalError::Faiss(e.to_string()))?;
        let path = dir.path().join("index.faiss");
        faiss::write_index(&self.index, path.to_string_lossy())?;
        std::fs::read(&path).map_err(|e| RetrievalError::Faiss(e.to_string()))
    }

    /// Read what [`GlobalIndex::to_bytes`] wrote; `dim` and `len` must agree with the index.
    pub fn from_bytes(bytes: &[u8], dim: usize, len: usize) -> Result<Self, RetrievalError> {
        let dir = tempfile::tempdir().map_err(|e| RetrievalError::Faiss(e.to_string()))?;
        let path = dir.path().join("index.faiss");
        std::fs::write(&path, bytes).map_err(|e| RetrievalError::Faiss(e.to_string()))?;
        let index = faiss::read_index(path.to_string_lossy())?;
        if index.d() as usize != dim || index.ntotal() as usize != len {
            return Err(RetrievalError::Input(format!(
                "the stored index holds {} vectors of {} dimensions, the map says {len} of {dim}",
                index.ntotal(),
                index.d()
            )));
        }
        let exact_among = EXACT_AMONG_TAGS.iter().any(|tag| bytes.starts_with(*tag));
        Ok(Self {
            index,
            dim,
            len,
            exact_among,
        })
    }

    /// Vector length.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of vectors.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The `k` most similar database vectors to `query`, best first.
    pub fn search(&mut self, query: &[f32], k: usize) -> Result<Vec<Hit>, RetrievalError> {
        crate::blas::single_threaded();
        if query.len() != self.dim {
            return Err(RetrievalError::Input(format!(
                "query has {} values, index is {}-d",
                query.len(),
                self.dim
            )));
        }
        let r = self.index.search(query, k.min(self.len))?;
        Ok(r.labels
            .iter()
            .zip(&r.distances)
            .filter_map(|(l, &score)| {
                l.get().map(|id| Hit {
                    id: id as usize,
                    score,
                })
            })
            .collect())
    }
}

impl GlobalIndex {
    /// The `k` most similar vectors among the ids `among` (a prior's region), best first.
    ///
    /// A flat or HNSW index scores each allowed id from its stored vector (exact ranking of the
    /// subset, nothing kept after the call: faiss's id selector, which this used before, is never
    /// freed by the `faiss` crate's `SearchParameters` and leaked about 2.5 KB a search). Index types
    /// that transform or bucket the vectors (IVF, PCA) rank what an ordinary search of depth
    /// max(8k, 1024) finds among the allowed ids. Allowed ids an approximate search misses follow
    /// the found ones in the order of `among` (the caller's, nearest first) with a score of
    /// `f32::MIN`, so a small region always yields all of its images. Ids outside the index are
    /// ignored.
    pub fn search_among(
        &mut self,
        query: &[f32],
        k: usize,
        among: &[usize],
    ) -> Result<Vec<Hit>, RetrievalError> {
        crate::blas::single_threaded();
        if query.len() != self.dim {
            return Err(RetrievalError::Input(format!(
                "query has {} values, index is {}-d",
                query.len(),
                self.dim
            )));
        }
        let allowed: Vec<usize> = among.iter().copied().filter(|&i| i < self.len).collect();
        let k = k.min(allowed.len());
        if k == 0 {
            return Ok(Vec::new());
        }
        let mut hits: Vec<Hit> = if self.exact_among {
            self.score_among(query, k, &allowed)?
        } else {
            // Index types that do not keep the vectors as they are searched (IVF cells, PCA):
            // rank what an ordinary, deeper search finds of the allowed ids.
            let deep = (k * 8).max(SEARCH_AMONG_DEPTH).min(self.len);
            let allowed_set: std::collections::HashSet<usize> = allowed.iter().copied().collect();
            let mut found = self.search(query, deep)?;
            found.retain(|h| allowed_set.contains(&h.id));
            found.truncate(k);
            found
        };
        for &id in &allowed {
            if hits.len() >= k {
                break;
            }
            if !hits.iter().any(|h| h.id == id) {
                hits.push(Hit {
                    id,
                    score: f32::MIN,
                });
            }
        }
        Ok(hits)
    }
}

impl GlobalIndex {
    /// The `k` best of `allowed` (ids inside the index) by inner product with their stored vectors,
    /// best first, ties by id. One `dim`-float buffer, reused for every id; nothing outlives the call.
    fn score_among(
        &self,
        query: &[f32],
        k: usize,
        allowed: &[usize],
    ) -> Result<Vec<Hit>, RetrievalError> {
        let mut vector = vec![0.0f32; self.dim];
        let mut hits = Vec::with_capacity(allowed.len());
        let mut seen = std::collections::HashSet::with_capacity(allowed.len());
        for &id in allowed {
            if !seen.insert(id) {
                continue;
            }
            self.index
                .reconstruct(faiss::Idx::new(id as u64), &mut vector)?;
            let score = vector.iter().zip(query).map(|(a, b)| a * b).sum();
            hits.push(Hit { id, score });
        }
        hits.sort_by(|a, b| b.score.total_cmp(&a.score).then(a.id.cmp(&b.id)));
        hits.truncate(k);
        Ok(hits)
    }
}

/// Exact top-k by inner product without faiss: the reference the tests hold the index to.
pub fn brute_force(vectors: &[f32], dim: usize, query: &[f32], k: usize) -> Vec<Hit> {
    let mut hits: Vec<Hit> = vectors
        .chunks_exact(dim)
        .enumerate()
        .map(|(id, v)| Hit {
            id,
            score: v.iter().zip(query).map(|(a, b)| a * b).sum(),
        })
        .collect();
    hits.sort_by(|a, b| b.score.total_cmp(&a.score).then(a.id.cmp(&b.id)));
    hits.truncate(k);
    hits
}
