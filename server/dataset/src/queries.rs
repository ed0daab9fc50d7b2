//! Walking a dataset's queries: every (Point file, query index) of some scenes, evenly thinned, and
//! their views read in order with the current Point file kept open. What evaluation, calibration
//! and a map's own calibration iterate over.

use crate::{DatasetError, PointEntry, Role, SceneEntry};

/// At most `max` items of `all`, evenly spaced (all of them when `max` is 0 or not smaller).
pub fn evenly_spaced<T>(all: Vec<T>, max: usize) -> Vec<T> {
    if max == 0 || max >= all.len() {
        return all;
    }
    let step = all.len() as f64 / max as f64;
    let mut keep = (0..max).map(|i| (i as f64 * step) as usize).peekable();
    all.into_iter()
        .enumerate()
        .filter_map(|(i, x)| (keep.next_if_eq(&i).is_some()).then_some(x))
        .collect()
}

/// Every query (Point file, query index) of `scenes`, evenly thinned to `max` (0 = all).
pub fn query_list<'a>(
    scenes: impl IntoIterator<Item = &'a SceneEntry>,
    max: usize,
) -> Result<Vec<(PointEntry, usize)>, DatasetError> {
    let mut all = Vec::new();
    for s in scenes {
        for p in &s.points {
            let n = p.open()?.count(Role::Query);
            all.extend((0..n).map(|q| (p.clone(), q)));
        }
    }
    Ok(evenly_spaced(all, max))
}

/// Reads query views of a [`query_list`] in order, keeping the current Point file open.
#[derive(Default)]
pub struct QueryViews {
    open: Option<(std::path::PathBuf, crate::PointReader)>,
}

impl QueryViews {
    /// Query `qi` of Point file `p`.
    pub fn view(&mut self, p: &PointEntry, qi: usize) -> Result<crate::View, DatasetError> {
        if self.open.as_ref().is_none_or(|o| o.0 != p.path) {
            self.open = Some((p.path.clone(), p.open()?));
        }
        self.open.as_ref().expect("opened").1.view(Role::Query, qi)
    }
}
