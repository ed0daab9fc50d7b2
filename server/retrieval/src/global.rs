//! One retrieval stage chosen by name: a describer (VLAD, ONNX model or BoW) and the store that
//! searches its descriptors (a faiss index for dense vectors, an inverted file for BoW).

use std::sync::Mutex;

use pntr_core::bytes::{Reader, Writer};
use pntr_core::RgbImage;
use pntr_features::Features;

use crate::bow::{BowParams, InvertedFile, Vocabulary};
use crate::index::{GlobalIndex, Hit, IndexKind};
use crate::onnx_global::OnnxGlobal;
use crate::vlad::Codebook;
use crate::RetrievalError;

/// Names of the global descriptors.
pub const METHODS: [&str; 3] = ["vlad", "onnx", "bow"];

/// Turns a query (its image and the local features already extracted) into a global descriptor.
#[derive(Debug)]
pub enum Describer {
    /// VLAD over the extractor's float descriptors, codebook learned on the map.
    Vlad(Codebook),
    /// A user-supplied ONNX model.
    Onnx(OnnxGlobal),
    /// TF-IDF bag of binary words over ORB descriptors, vocabulary learned on the map.
    Bow(Vocabulary),
}

/// A global descriptor: dense (VLAD, ONNX) or a sparse BoW vector.
#[derive(Debug, Clone, PartialEq)]
pub enum Descriptor {
    /// L2-normalised vector.
    Dense(Vec<f32>),
    /// L1-normalised (word, weight) list sorted by word.
    Bow(Vec<(u32, f32)>),
}

/// How to learn a describer from the map's images.
#[derive(Debug, Clone, PartialEq)]
pub enum Method {
    /// VLAD with this many codewords.
    Vlad {
        /// Codewords. Default 64.
        words: usize,
    },
    /// BoW with this vocabulary shape.
    Bow(BowParams),
}

impl Describer {
    /// Learn a VLAD codebook or BoW vocabulary from the map's database features.
    pub fn train(method: &Method, db: &[Features]) -> Result<Self, RetrievalError> {
        match method {
            Method::Vlad { words } => {
                let dim = db.iter().map(|f| f.dim).find(|&d| d > 0).ok_or_else(|| {
                    RetrievalError::Input(
                        "VLAD needs float descriptors; this extractor gives none (use bow for orb)"
                            .into(),
                    )
                })?;
                let all: Vec<f32> = db
                    .iter()
                    .flat_map(|f| f.descriptors.iter().copied())
                    .collect();
                Ok(Self::Vlad(Codebook::train(&all, dim, *words, 1)?))
            }
            Method::Bow(p) => {
                let images: Vec<Vec<[u8; 32]>> = db.iter().map(|f| f.binary.clone()).collect();
                if images.iter().all(|b| b.is_empty()) {
                    return Err(RetrievalError::Input(
                        "BoW needs binary (ORB) descriptors; this extractor gives none".into(),
                    ));
                }
                Ok(Self::Bow(Vocabulary::train(&images, *p)?))
            }
        }
    }

    /// The method's name (one of [`METHODS`]).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Vlad(_) => "vlad",
            Self::Onnx(_) => "onnx",
            Self::Bow(_) => "bow",
        }
    }

    /// The descriptor of an image from its local features alone (VLAD, BoW); the ONNX describer needs
    /// the image and refuses.
    pub fn describe_features(&self, features: &Features) -> Result<Descriptor, RetrievalError> {
        match self {
            Self::Onnx(_) => Err(RetrievalError::Input(
                "the onnx global descriptor needs the image".into(),
            )),
            _ => self.describe(
                &RgbImage {
                    width: 0,
                    height: 0,
                    data: Vec::new(),
                },
                features,
            ),
        }
    }

    /// The global descriptor of an image whose local `features` are already extracted.
    pub fn describe(
        &self,
        image: &RgbImage,
        features: &Features,
    ) -> Result<Descriptor, RetrievalError> {
        match self {
            Self::Vlad(book) => {
                if features.dim != book.dim {
                    return Err(RetrievalError::Input(format!(
                        "VLAD codebook is for {}-d descriptors, the features are {}-d",
                        book.dim, features.dim
                    )));
                }
                Ok(Descriptor::Dense(book.vlad(&features.descriptors)?))
            }
            Self::Onnx(m) => Ok(Descriptor::Dense(m.describe(image)?)),
            Self::Bow(v) => Ok(Descriptor::Bow(v.bow(&features.binary))),
        }
    }
}

enum Store {
    Dense(Mutex<GlobalIndex>, IndexKind),
    Bow(InvertedFile, Vec<Vec<(u32, f32)>>),
}

/// A describer with the searchable descriptors of every database image (ids = map order).
pub struct Retriever {
    /// The describer.
    pub describer: Describer,
    store: Store,
}

impl std::fmt::Debug for Retriever {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "Retriever({}, {} images)",
            self.describer.name(),
            self.len()
        )
    }
}

impl Retriever {
    /// Index the database descriptors (all of the describer's kind) with `kind` for dense ones.
    pub fn build(
        describer: Describer,
        descriptors: Vec<Descriptor>,
        kind: IndexKind,
    ) -> Result<Self, RetrievalError> {
        let store = match &describer {
            Describer::Bow(voc) => {
                let vecs = descriptors
                    .into_iter()
                    .map(|d| match d {
                        Descriptor::Bow(v) => Ok(v),
                        Descriptor::Dense(_) => Err(RetrievalError::Input(
                            "a dense descriptor in a BoW map".into(),
                        )),
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                Store::Bow(InvertedFile::build(voc.words(), &vecs)?, vecs)
            }
            _ => {
                let mut dim = 0;
                let mut flat = Vec::new();
                for d in descriptors {
                    match d {
                        Descriptor::Dense(v) => {
                            dim = v.len();
                            flat.extend(v);
                        }
                        Descriptor::Bow(_) => {
                            return Err(RetrievalError::Input(
                                "a BoW descriptor in a dense map".into(),
                            ))
                        }
                    }
                }
                // What `auto` chose is what the map records.
                let kind = kind.resolve(flat.len() / dim.max(1), dim);
                Store::Dense(Mutex::new(GlobalIndex::build(&flat, dim, kind)?), kind)
            }
        };
        Ok(Self { describer, store })
    }

    /// Append database images (their descriptors, of the describer's kind) after the ones indexed,
    /// keeping what was learned: the VLAD codebook or BoW vocabulary and, for a dense index, its
    /// training (PCA-whitening, IVF cells); ids continue from [`Retriever::len`]. How a map is
    /// extended without relearning it. Errors: a descriptor of another kind or length.
    pub fn extend(&mut self, descriptors: Vec<Descriptor>) -> Result<(), RetrievalError> {
        match &mut self.store {
            Store::Bow(inv, vecs) => {
                let Describer::Bow(voc) = &self.describer else {
                    return Err(RetrievalError::Input(
                        "a BoW store without a vocabulary".into(),
                    ));
                };
                for d in descriptors {
                    match d {
                        Descriptor::Bow(v) => vecs.push(v),
                        Descriptor::Dense(_) => {
                            return Err(RetrievalError::Input(
                                "a dense descriptor in a BoW map".into(),
                            ))
                        }
                    }
                }
                *inv = InvertedFile::build(voc.words(), vecs)?;
            }
            Store::Dense(index, _) => {
                let index = index
                    .get_mut()
                    .map_err(|_| RetrievalError::Faiss("a previous search panicked".into()))?;
                let mut flat = Vec::new();
                for d in descriptors {
                    match d {
                        Descriptor::Dense(v) if v.len() == index.dim() => flat.extend(v),
                        Descriptor::Dense(v) => {
                            return Err(RetrievalError::Input(format!(
                                "a {}-d descriptor for a {}-d index",
                                v.len(),
                                index.dim()
                            )))
                        }
                        Descriptor::Bow(_) => {
                            return Err(RetrievalError::Input(
                                "a BoW descriptor in a dense map".into(),
                            ))
                        }
                    }
                }
                index.add(&flat)?;
            }
        }
        Ok(())
    }

    /// Number of database images.
    pub fn len(&self) -> usize {
        match &self.store {
            Store::Dense(i, _) => i.lock().map(|i| i.len()).unwrap_or(0),
            Store::Bow(inv, _) => inv.len(),
        }
    }

    /// True when the map is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The index kind of a dense store (`None` for BoW).
    pub fn index_kind(&self) -> Option<IndexKind> {
        match &self.store {
            Store::Dense(_, k) => Some(*k),
            Store::Bow(..) => None,
        }
    }

    /// The `k` most similar database images, best first.
    pub fn search(&self, query: &Descriptor, k: usize) -> Result<Vec<Hit>, RetrievalError> {
        match (&self.store, query) {
            (Store::Dense(index, _), Descriptor::Dense(q)) => index
                .lock()
                .map_err(|_| RetrievalError::Faiss("a previous search panicked".into()))?
                .search(q, k),
            (Store::Bow(inv, _), Descriptor::Bow(q)) => Ok(inv.search(q, k)),
            _ => Err(RetrievalError::Input(
                "the query descriptor is not of the map's kind".into(),
            )),
        }
    }

    /// The `k` most similar among the database images `among` (map order ids, the caller's preferred
    /// order first), best first; see [`GlobalIndex::search_among`] for approximate indexes.
    pub fn search_among(
        &self,
        query: &Descriptor,
        k: usize,
        among: &[usize],
    ) -> Result<Vec<Hit>, RetrievalError> {
        match (&self.store, query) {
            (Store::Dense(index, _), Descriptor::Dense(q)) => index
                .lock()
                .map_err(|_| RetrievalError::Faiss("a previous search panicked".into()))?
                .search_among(q, k, among),
            (Store::Bow(_, vecs), Descriptor::Bow(q)) => {
                let mut hits: Vec<Hit> = among
                    .iter()
                    .filter_map(|&id| {
                        vecs.get(id).map(|v| Hit {
                            id,
                            score: crate::bow::l1_score(q, v),
                        })
                    })
                    .collect();
                hits.sort_by(|a, b| b.score.total_cmp(&a.score).then(a.id.cmp(&b.id)));
                hits.truncate(k);
                Ok(hits)
            }
            _ => Err(RetrievalError::Input(
                "the query descriptor is not of the map's kind".into(),
            )),
        }
    }

    /// Serialise the describer's learned part and the store. An ONNX describer stores nothing of the
    /// model (the map records the model's identity; the model is loaded from its file).
    pub fn to_bytes(&self) -> Result<Vec<u8>, RetrievalError> {
        let mut w = Writer::new();
        w.str(self.describer.name());
        match &self.describer {
            Describer::Vlad(b) => w.blob(&b.to_bytes()),
            Describer::Bow(v) => w.blob(&v.to_bytes()),
            Describer::Onnx(m) => w.u64(m.dim() as u64),
        }
        match &self.store {
            Store::Dense(index, kind) => {
                let index = index
                    .lock()
                    .map_err(|_| RetrievalError::Faiss("a previous search panicked".into()))?;
                w.str(&kind.name());
                w.u64(index.dim() as u64);
                w.u64(index.len() as u64);
                w.blob(&index.to_bytes()?);
            }
            Store::Bow(_, vecs) => {
                w.u64(vecs.len() as u64);
                for v in vecs {
                    w.u64(v.len() as u64);
                    for &(word, x) in v {
                        w.u32(word);
                        w.f32(x);
                    }
                }
            }
        }
        Ok(w.bytes)
    }

    /// Read what [`Retriever::to_bytes`] wrote. `onnx` loads the model for a map built with one.
    pub fn from_bytes(
        bytes: &[u8],
        onnx: impl FnOnce(usize) -> Result<OnnxGlobal, RetrievalError>,
    ) -> Result<Self, RetrievalError> {
        let mut r = Reader::new(bytes, "retrieval section");
        let name = r.str()?;
        let describer = match name.as_str() {
            "vlad" => Describer::Vlad(
                Codebook::from_bytes(r.blob()?)
                    .map_err(|m| RetrievalError::Input(format!("VLAD codebook: {m}")))?,
            ),
            "bow" => Describer::Bow(Vocabulary::from_bytes(r.blob()?)?),
            "onnx" => {
                let dim = r.u64()? as usize;
                Describer::Onnx(onnx(dim)?)
            }
            other => {
                return Err(RetrievalError::Input(format!(
                    "unknown global descriptor `{other}`"
                )))
            }
        };
        let store = if let Describer::Bow(voc) = &describer {
            let n = r.u64()? as usize;
            let mut vecs = Vec::with_capacity(n.min(r.remaining() / 8));
            for _ in 0..n {
                let m = r.u64()? as usize;
                let mut v = Vec::with_capacity(m.min(r.remaining() / 8));
                for _ in 0..m {
                    v.push((r.u32()?, r.f32()?));
                }
                vecs.push(v);
            }
            Store::Bow(InvertedFile::build(voc.words(), &vecs)?, vecs)
        } else {
            let kind = IndexKind::parse(&r.str()?)?;
            let dim = r.u64()? as usize;
            let len = r.u64()? as usize;
            let index = GlobalIndex::from_bytes(r.blob()?, dim, len)?;
            Store::Dense(Mutex::new(index), kind)
        };
        r.finish()?;
        Ok(Self { describer, store })
    }
}
