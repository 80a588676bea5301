//! The classes a transfer chooses from: class prompts and the label each one writes.

use profuse_formats::{FileKind, Prompts};

use crate::error::{Result, TransferError};
use crate::Source;

/// Class prompts with unit embeddings, grouped into classes.
///
/// Classes are the distinct labels in ascending order; their position is the *class
/// index* (argmax ties go to the smaller index, i.e. the smaller label). Several prompts
/// may name the same class (synonyms): the softmax runs over prompts and a class's
/// probability is the sum over its prompts.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassSet {
    labels: Vec<i32>,
    names: Vec<String>,
    prompt_class: Vec<usize>,
    embeddings: Vec<f32>,
    dim: usize,
    file: String,
    label_space: Option<String>,
}

impl ClassSet {
    /// Every prompt with `class_ids >= 0` is a class prompt; the label it writes is its
    /// class id. Errors when the file has no `class_ids` or every id is −1.
    pub fn from_prompts(prompts: Source<'_, Prompts>) -> Result<ClassSet> {
        let (file, p) = (prompts.file, prompts.data);
        p.validate(file)?;
        let Some(ids) = &p.class_ids else {
            return Err(TransferError::NoClassPrompts {
                file: file.to_string(),
                detail:
                    "the file has no `class_ids` tensor; name the class prompts instead (--classes)"
                        .to_string(),
            });
        };
        let rows: Vec<(usize, i32)> = ids
            .iter()
            .enumerate()
            .filter(|(_, c)| **c >= 0)
            .map(|(q, c)| (q, *c))
            .collect();
        if rows.is_empty() {
            return Err(TransferError::NoClassPrompts {
                file: file.to_string(),
                detail: format!("all {} entries of `class_ids` are -1", ids.len()),
            });
        }
        Ok(Self::build(p, file, &rows, label_space_of(p, true)))
    }

    /// The prompts named in `names` are the classes. With `class_ids` in the file each
    /// writes its class id (and must have one >= 0); without, the label is the name's
    /// position in `names`.
    pub fn from_names(prompts: Source<'_, Prompts>, names: &[String]) -> Result<ClassSet> {
        let (file, p) = (prompts.file, prompts.data);
        p.validate(file)?;
        if names.is_empty() {
            return Err(TransferError::NoClassPrompts {
                file: file.to_string(),
                detail: "the list of class prompt names is empty".to_string(),
            });
        }
        let bad = |detail: String| TransferError::BadClassPrompt {
            file: file.to_string(),
            detail,
        };
        let mut rows = Vec::with_capacity(names.len());
        for (position, name) in names.iter().enumerate() {
            if names[..position].contains(name) {
                return Err(bad(format!("class prompt {name:?} is listed twice")));
            }
            let q = p.index_of(name).ok_or_else(|| {
                bad(format!(
                    "no prompt {name:?} (the file has {} prompts)",
                    p.len()
                ))
            })?;
            let label = match &p.class_ids {
                Some(ids) if ids[q] < 0 => {
                    return Err(bad(format!(
                        "prompt {name:?} has class_id -1 (a distractor or negative, not a class)"
                    )))
                }
                Some(ids) => ids[q],
                None => i32::try_from(position).map_err(|_| bad("too many names".to_string()))?,
            };
            rows.push((q, label));
        }
        let space = label_space_of(p, p.class_ids.is_some());
        Ok(Self::build(p, file, &rows, space))
    }

    /// The classes whose label is in `labels`, with only their prompts: the vocabulary of a
    /// class set (OpenGaussian's ScanNet protocol labels every vertex by argmax over the
    /// evaluated set's prompts only, e.g. the 19 NYU40 ids). The softmax then runs over
    /// these prompts alone. Errors when no class of `self` has a label in `labels`.
    pub fn restrict(&self, labels: &[i32]) -> Result<ClassSet> {
        let keep: Vec<usize> = (0..self.prompts())
            .filter(|&q| labels.contains(&self.labels[self.prompt_class[q]]))
            .collect();
        if keep.is_empty() {
            return Err(TransferError::NoClassPrompts {
                file: self.file.clone(),
                detail: format!(
                    "none of the labels {labels:?} is a class (the classes are {:?})",
                    self.labels
                ),
            });
        }
        let mut kept_labels: Vec<i32> = keep
            .iter()
            .map(|&q| self.labels[self.prompt_class[q]])
            .collect();
        kept_labels.sort_unstable();
        kept_labels.dedup();
        let names = kept_labels
            .iter()
            .map(|l| {
                self.labels
                    .binary_search(l)
                    .map_or_else(|_| String::new(), |c| self.names[c].clone())
            })
            .collect();
        let prompt_class = keep
            .iter()
            .map(|&q| {
                kept_labels
                    .binary_search(&self.labels[self.prompt_class[q]])
                    .unwrap_or(0)
            })
            .collect();
        let mut embeddings = Vec::with_capacity(keep.len() * self.dim);
        for &q in &keep {
            embeddings.extend_from_slice(self.prompt_embedding(q));
        }
        Ok(ClassSet {
            labels: kept_labels,
            names,
            prompt_class,
            embeddings,
            dim: self.dim,
            file: self.file.clone(),
            label_space: self.label_space.clone(),
        })
    }

    fn build(
        p: &Prompts,
        file: &str,
        rows: &[(usize, i32)],
        label_space: Option<String>,
    ) -> ClassSet {
        let mut labels: Vec<i32> = rows.iter().map(|r| r.1).collect();
        labels.sort_unstable();
        labels.dedup();
        // The first prompt (in file order) of each class names it.
        let names = labels
            .iter()
            .map(|l| {
                rows.iter()
                    .filter(|r| r.1 == *l)
                    .map(|r| r.0)
                    .min()
                    .map_or_else(String::new, |q| p.names[q].clone())
            })
            .collect();
        let prompt_class = rows
            .iter()
            .map(|r| labels.binary_search(&r.1).unwrap_or(0))
            .collect();
        let mut embeddings = Vec::with_capacity(rows.len() * p.dim);
        for &(q, _) in rows {
            embeddings.extend(unit(p.embedding(q)));
        }
        ClassSet {
            labels,
            names,
            prompt_class,
            embeddings,
            dim: p.dim,
            file: file.to_string(),
            label_space,
        }
    }

    /// Number of classes.
    pub fn len(&self) -> usize {
        self.labels.len()
    }

    /// Whether there are none (never true for a constructed set).
    pub fn is_empty(&self) -> bool {
        self.labels.is_empty()
    }

    /// The label written for each class index, ascending.
    pub fn labels(&self) -> &[i32] {
        &self.labels
    }

    /// The name of each class (its first prompt in file order).
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Embedding dimension D.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of class prompts (>= classes when synonyms share a class).
    pub fn prompts(&self) -> usize {
        self.prompt_class.len()
    }

    /// The prompts file (or in-memory label) the classes came from.
    pub fn file(&self) -> &str {
        &self.file
    }

    /// The label space of the written labels: the prompts' `label_space` metadata if set;
    /// else `None` when the labels are class ids (the caller may know it, e.g. from the
    /// mesh), or `Some("classes")` when they are positions in a list of names.
    pub fn label_space(&self) -> Option<&str> {
        self.label_space.as_deref()
    }

    /// Unit embedding of class prompt `q`.
    pub(crate) fn prompt_embedding(&self, q: usize) -> &[f32] {
        &self.embeddings[q * self.dim..(q + 1) * self.dim]
    }

    /// Class index of class prompt `q`.
    pub(crate) fn prompt_class(&self, q: usize) -> usize {
        self.prompt_class[q]
    }
}

fn label_space_of(p: &Prompts, labels_are_class_ids: bool) -> Option<String> {
    match p.extra.get("label_space") {
        Some(space) if labels_are_class_ids => Some(space.clone()),
        _ if labels_are_class_ids => None,
        _ => Some("classes".to_string()),
    }
}

/// `v / |v|` (norm in f64); validated prompt rows are never zero.
fn unit(v: &[f32]) -> impl Iterator<Item = f32> + '_ {
    let norm = v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
    let inv = if norm > 0.0 { 1.0 / norm } else { 0.0 };
    v.iter().map(move |x| (f64::from(*x) * inv) as f32)
}
