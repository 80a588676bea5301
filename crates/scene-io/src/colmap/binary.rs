//! COLMAP binary model: `cameras.bin`, `images.bin`, `points3D.bin`, little-endian, in
//! the layout of COLMAP's `read_write_model.py`:
//!
//! * cameras: u64 count; per camera i32 id, i32 model id, u64 width, u64 height,
//!   f64 × (model's parameter count);
//! * images: u64 count; per image i32 id, f64 qvec[4], f64 tvec[3], i32 camera id,
//!   NUL-terminated name, u64 point count, (f64 x, f64 y, i64 point3D id) per point;
//! * points3D: u64 count; per point u64 id, f64 xyz[3], u8 rgb[3], f64 error,
//!   u64 track length, (i32 image id, i32 point2D index) per element.
//!
//! Ids are read as unsigned 32-bit (COLMAP's `camera_t`, `image_t`); counts never
//! reserve more memory than the bytes left could hold.

use std::collections::BTreeMap;
use std::path::Path;

use super::model::{insert_camera, CameraModel, ColmapCamera, ColmapImage, ColmapPoint};
use crate::error::{invalid, truncated, unsupported, Result};
use crate::fsutil::{read_bytes, show};

/// Little-endian reads with errors naming the record and field that ran out of bytes.
struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
    label: String,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &dyn Fn() -> String) -> Result<&'a [u8]> {
        let slice = self
            .pos
            .checked_add(n)
            .and_then(|end| self.bytes.get(self.pos..end));
        match slice {
            Some(s) => {
                self.pos += n;
                Ok(s)
            }
            None => Err(truncated(
                &self.label,
                format!(
                    "{} needs {n} bytes at offset {}, the file has {}",
                    what(),
                    self.pos,
                    self.bytes.len()
                ),
            )),
        }
    }

    fn array<const N: usize>(&mut self, what: &dyn Fn() -> String) -> Result<[u8; N]> {
        let s = self.take(N, what)?;
        let mut out = [0u8; N];
        out.copy_from_slice(s);
        Ok(out)
    }

    fn u64(&mut self, what: &dyn Fn() -> String) -> Result<u64> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }

    fn i64(&mut self, what: &dyn Fn() -> String) -> Result<i64> {
        Ok(i64::from_le_bytes(self.array(what)?))
    }

    fn u32(&mut self, what: &dyn Fn() -> String) -> Result<u32> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    fn i32(&mut self, what: &dyn Fn() -> String) -> Result<i32> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }

    fn u8(&mut self, what: &dyn Fn() -> String) -> Result<u8> {
        Ok(self.array::<1>(what)?[0])
    }

    fn f64(&mut self, what: &dyn Fn() -> String) -> Result<f64> {
        let v = f64::from_le_bytes(self.array(what)?);
        if v.is_finite() {
            Ok(v)
        } else {
            Err(invalid(
                &self.label,
                what(),
                format!("{v}, expected a finite number"),
            ))
        }
    }

    /// A count, with the smallest record size, so that a lying count cannot make us
    /// reserve memory the file could not fill.
    fn count(&mut self, what: &dyn Fn() -> String, min_record: usize) -> Result<(usize, usize)> {
        let raw = self.u64(what)?;
        let n = usize::try_from(raw).map_err(|_| {
            invalid(
                &self.label,
                what(),
                format!("count {raw} does not fit in memory"),
            )
        })?;
        let left = self.bytes.len().saturating_sub(self.pos);
        Ok((n, n.min(left / min_record.max(1))))
    }

    fn c_string(&mut self, what: &dyn Fn() -> String) -> Result<String> {
        let rest = self.bytes.get(self.pos..).unwrap_or_default();
        let len = rest.iter().position(|b| *b == 0).ok_or_else(|| {
            truncated(
                &self.label,
                format!("{} has no terminating NUL byte", what()),
            )
        })?;
        let raw = self.take(len + 1, what)?;
        let name = raw.get(..len).unwrap_or_default();
        String::from_utf8(name.to_vec())
            .map_err(|_| invalid(&self.label, what(), "is not valid UTF-8"))
    }

    fn finish(&self, what: &str) -> Result<()> {
        if self.pos == self.bytes.len() {
            Ok(())
        } else {
            Err(invalid(
                &self.label,
                what,
                format!(
                    "{} trailing bytes after the last record (the count disagrees with the data)",
                    self.bytes.len() - self.pos
                ),
            ))
        }
    }
}

fn reader<'a>(bytes: &'a [u8], path: &Path) -> Reader<'a> {
    Reader {
        bytes,
        pos: 0,
        label: show(path),
    }
}

pub(crate) fn read_cameras(path: &Path) -> Result<BTreeMap<u32, ColmapCamera>> {
    let bytes = read_bytes(path)?;
    let mut r = reader(&bytes, path);
    let (n, _) = r.count(&|| "camera count".to_string(), 24)?;
    let mut cameras = BTreeMap::new();
    for i in 0..n {
        let what = |field: &'static str| move || format!("camera record {i} field {field}");
        let id = r.u32(&what("camera_id"))?;
        let model_id = r.i32(&what("model_id"))?;
        let model = CameraModel::from_id(model_id).ok_or_else(|| {
            unsupported(
                &r.label,
                "camera model",
                format!("camera {id} has model id {model_id}, not a COLMAP camera model (0..=11)"),
            )
        })?;
        let width = r.u64(&what("width"))?;
        let height = r.u64(&what("height"))?;
        let params = (0..model.num_params())
            .map(|p| r.f64(&move || format!("camera {id} ({}) params[{p}]", model.name())))
            .collect::<Result<Vec<_>>>()?;
        insert_camera(
            &mut cameras,
            ColmapCamera {
                id,
                model,
                width,
                height,
                params,
            },
            &r.label,
            format!("camera record {i} camera_id"),
        )?;
    }
    r.finish("camera records")?;
    Ok(cameras)
}

pub(crate) fn read_images(path: &Path) -> Result<Vec<ColmapImage>> {
    let bytes = read_bytes(path)?;
    let mut r = reader(&bytes, path);
    let (n, cap) = r.count(&|| "image count".to_string(), 73)?;
    let mut images = Vec::with_capacity(cap);
    for i in 0..n {
        let what = |field: &'static str| move || format!("image record {i} field {field}");
        let id = r.u32(&what("image_id"))?;
        let mut qvec = [0.0; 4];
        for slot in &mut qvec {
            *slot = r.f64(&what("qvec"))?;
        }
        let mut tvec = [0.0; 3];
        for slot in &mut tvec {
            *slot = r.f64(&what("tvec"))?;
        }
        let camera_id = r.u32(&what("camera_id"))?;
        let name = r.c_string(&what("name"))?;
        let (count, cap) = r.count(&what("num_points2D"), 24)?;
        let mut points2d = Vec::with_capacity(cap);
        for p in 0..count {
            let pt = move || format!("image {id} points2D[{p}]");
            let x = r.f64(&pt)?;
            let y = r.f64(&pt)?;
            let point3d = r.i64(&pt)?;
            points2d.push(([x, y], point3d));
        }
        images.push(ColmapImage {
            id,
            qvec,
            tvec,
            camera_id,
            name,
            points2d,
        });
    }
    r.finish("image records")?;
    Ok(images)
}

pub(crate) fn read_points(path: &Path) -> Result<Vec<ColmapPoint>> {
    let bytes = read_bytes(path)?;
    let mut r = reader(&bytes, path);
    let (n, cap) = r.count(&|| "point count".to_string(), 51)?;
    let mut points = Vec::with_capacity(cap);
    for i in 0..n {
        let what = |field: &'static str| move || format!("point3D record {i} field {field}");
        let id = r.u64(&what("point3D_id"))?;
        let xyz = [
            r.f64(&what("xyz"))?,
            r.f64(&what("xyz"))?,
            r.f64(&what("xyz"))?,
        ];
        let rgb = [
            r.u8(&what("rgb"))?,
            r.u8(&what("rgb"))?,
            r.u8(&what("rgb"))?,
        ];
        let error = r.f64(&what("error"))?;
        let (len, cap) = r.count(&what("track_length"), 8)?;
        let mut track = Vec::with_capacity(cap);
        for _ in 0..len {
            let image = r.u32(&what("track image_id"))?;
            let idx = r.u32(&what("track point2D_idx"))?;
            track.push((image, idx));
        }
        points.push(ColmapPoint {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    r.finish("point3D records")?;
    Ok(points)
}
