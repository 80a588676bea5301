//! Mask descriptors from the SAM image embedding: the average of the 256-d embedding
//! over the mask, weighted by how many of the mask's pixels fall into each 16 x 16 cell,
//! L2-normalised.

use crate::sam::{resized_size, Embedding, EMBED_DIM, EMBED_SIDE, INPUT_SIZE};

/// The embedding cell of each column (or row) of a mask grid of `cells` samples over an
/// image side that SAM resized to `resized` pixels (sample centres mapped into the 1024
/// frame, 16 pixels per cell).
fn cell_of(cells: usize, resized: usize) -> Vec<usize> {
    let per_cell = (INPUT_SIZE / EMBED_SIDE) as f64;
    (0..cells)
        .map(|i| {
            let u = (i as f64 + 0.5) * resized as f64 / cells as f64;
            ((u / per_cell).floor() as usize).min(EMBED_SIDE - 1)
        })
        .collect()
}

/// One unit descriptor per local mask index `0..masks` of a label map of `grid` =
/// (height, width) (`u16::MAX` = no mask). A mask without pixels gets the mean embedding
/// of the whole image instead (the masks file needs a unit row; the generator never
/// writes empty masks). Row-major [masks, 256].
pub fn pool_embedding(
    emb: &Embedding,
    labels: &[u16],
    grid: (usize, usize),
    masks: usize,
) -> Vec<f32> {
    let (h, w) = grid;
    let (nw, nh) = resized_size(emb.image_width, emb.image_height);
    let cx = cell_of(w, nw);
    let cy = cell_of(h, nh);
    let cells = EMBED_SIDE * EMBED_SIDE;
    let mut hist = vec![0u32; masks * cells];
    for y in 0..h {
        for x in 0..w {
            let l = labels[y * w + x];
            if l != u16::MAX && usize::from(l) < masks {
                hist[usize::from(l) * cells + cy[y] * EMBED_SIDE + cx[x]] += 1;
            }
        }
    }
    let mut out = vec![0f32; masks * EMBED_DIM];
    for m in 0..masks {
        let mut h_m = hist[m * cells..(m + 1) * cells].to_vec();
        if h_m.iter().all(|c| *c == 0) {
            h_m.iter_mut().for_each(|c| *c = 1);
        }
        let row = &mut out[m * EMBED_DIM..(m + 1) * EMBED_DIM];
        let mut acc = vec![0f64; EMBED_DIM];
        for (c, &n) in h_m.iter().enumerate().filter(|(_, n)| **n > 0) {
            for (d, a) in acc.iter_mut().enumerate() {
                *a += f64::from(n) * f64::from(emb.data[d * cells + c]);
            }
        }
        let norm = acc.iter().map(|a| a * a).sum::<f64>().sqrt();
        for (r, a) in row.iter_mut().zip(&acc) {
            *r = if norm > 0.0 { (a / norm) as f32 } else { 0.0 };
        }
        if norm == 0.0 {
            row[0] = 1.0;
        }
    }
    out
}
