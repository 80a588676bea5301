//! Run-length encoded binary masks (the generator keeps hundreds of candidates per view)
//! and 8-connected component labelling.

/// A binary mask as alternating run lengths in row-major order, starting with a run of
/// unset pixels (possibly empty).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rle {
    runs: Vec<u32>,
}

impl Rle {
    /// Encodes a mask.
    pub fn encode(bits: &[bool]) -> Rle {
        let mut runs = Vec::new();
        let mut current = false;
        let mut len = 0u32;
        for &b in bits {
            if b != current {
                runs.push(len);
                len = 0;
                current = b;
            }
            len += 1;
        }
        runs.push(len);
        Rle { runs }
    }

    /// Decodes into `n` pixels.
    pub fn decode(&self, n: usize) -> Vec<bool> {
        let mut out = vec![false; n];
        self.for_each_set(|i| out[i] = true);
        out
    }

    /// Calls `f` with the index of every set pixel, in order.
    pub fn for_each_set(&self, mut f: impl FnMut(usize)) {
        let mut pos = 0usize;
        for (k, &r) in self.runs.iter().enumerate() {
            if k % 2 == 1 {
                (pos..pos + r as usize).for_each(&mut f);
            }
            pos += r as usize;
        }
    }

    /// Number of set pixels.
    pub fn area(&self) -> usize {
        self.runs
            .iter()
            .skip(1)
            .step_by(2)
            .map(|r| *r as usize)
            .sum()
    }

    /// Inclusive bounding box (x0, y0, x1, y1) on a grid of width `w`; `None` if empty.
    pub fn bbox(&self, w: usize) -> Option<[usize; 4]> {
        let mut b: Option<[usize; 4]> = None;
        let mut pos = 0usize;
        for (k, &r) in self.runs.iter().enumerate() {
            let r = r as usize;
            if k % 2 == 1 && r > 0 {
                let (first, last) = (pos, pos + r - 1);
                let (y0, y1) = (first / w, last / w);
                // A run spanning rows covers full rows in between.
                let (xa, xb) = if y0 == y1 {
                    (first % w, last % w)
                } else {
                    (0, w - 1)
                };
                b = Some(match b {
                    None => [xa, y0, xb, y1],
                    Some(o) => [o[0].min(xa), o[1].min(y0), o[2].max(xb), o[3].max(y1)],
                });
            }
            pos += r;
        }
        b
    }
}

/// 8-connected components of the set pixels: a label per pixel (0 = unset, components
/// numbered from 1 in scan order of their first pixel) and each component's size.
pub fn connected_components(bits: &[bool], grid: (usize, usize)) -> (Vec<u32>, Vec<usize>) {
    let (h, w) = grid;
    let mut labels = vec![0u32; h * w];
    let mut sizes = Vec::new();
    let mut stack = Vec::new();
    for start in 0..h * w {
        if !bits[start] || labels[start] != 0 {
            continue;
        }
        sizes.push(0usize);
        let id = sizes.len() as u32;
        labels[start] = id;
        stack.push(start);
        while let Some(i) = stack.pop() {
            sizes[id as usize - 1] += 1;
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            for dy in -1..=1isize {
                for dx in -1..=1isize {
                    let (nx, ny) = (x + dx, y + dy);
                    if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                        continue;
                    }
                    let j = ny as usize * w + nx as usize;
                    if bits[j] && labels[j] == 0 {
                        labels[j] = id;
                        stack.push(j);
                    }
                }
            }
        }
    }
    (labels, sizes)
}
