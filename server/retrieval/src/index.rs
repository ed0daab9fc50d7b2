//! The global-descriptor index: faiss with inner product on L2-normalised vectors.

use faiss::index::IndexImpl;
use faiss::{Index, MetricType};

use crate::RetrievalError;

/// Which faiss index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IndexKind {
    /// Exact search (default; fine up to tens of thousands of images).
    Flat,
    /// HNSW graph with `m` links per node: approximate, for maps of 100k images and more.
    Hnsw {
        /// Links per node.
        m: u32,
    },
}

/// A searchable set of global descriptors; ids are insertion order.
pub struct GlobalIndex {
    index: IndexImpl,
    dim: usize,
    len: usize,
}

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
    /// Build from `vectors` (`n * dim` values).
    pub fn build(vectors: &[f32], dim: usize, kind: IndexKind) -> Result<Self, RetrievalError> {
        if dim == 0 || vectors.len() % dim != 0 {
            return Err(RetrievalError::Input(format!(
                "{} values are not {dim}-d vectors",
                vectors.len()
            )));
        }
        let desc = match kind {
            IndexKind::Flat => "Flat".to_string(),
            IndexKind::Hnsw { m } => format!("HNSW{m},Flat"),
        };
        let mut index = faiss::index_factory(dim as u32, desc, MetricType::InnerProduct)?;
        index.add(vectors)?;
        Ok(Self {
            index,
            dim,
            len: vectors.len() / dim,
        })
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
