//! A small, strict PLY reader: the header (format, elements, scalar and list properties,
//! comments) and the body in `ascii 1.0` or `binary_little_endian 1.0`, stored column by
//! column in each property's own type (a 6-million-Gaussian degree-3 scene stays 1.5 GB,
//! not 3 GB as f64 would make it).
//!
//! Every element is parsed, including ones nobody asked for, because in a binary file the
//! only way past an element with list properties is to read its lists.

use std::path::Path;

use crate::error::{header_err, invalid, parse_err, truncated, unsupported, Result};
use crate::fsutil::{read_bytes, show};

/// Encoding of the PLY body.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlyFormat {
    /// `format ascii 1.0`: one element instance per line, whitespace-separated tokens.
    Ascii,
    /// `format binary_little_endian 1.0`: packed little-endian values, no padding.
    BinaryLittleEndian,
}

impl PlyFormat {
    /// The name used in the `format` header line.
    pub fn name(self) -> &'static str {
        match self {
            PlyFormat::Ascii => "ascii",
            PlyFormat::BinaryLittleEndian => "binary_little_endian",
        }
    }
}

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    /// Parses both the classic names (`uchar`, `float`) and the sized ones (`uint8`,
    /// `float32`).
    pub fn parse(name: &str) -> Option<ScalarType> {
        Some(match name {
            "char" | "int8" => ScalarType::I8,
            "uchar" | "uint8" => ScalarType::U8,
            "short" | "int16" => ScalarType::I16,
            "ushort" | "uint16" => ScalarType::U16,
            "int" | "int32" => ScalarType::I32,
            "uint" | "uint32" => ScalarType::U32,
            "float" | "float32" => ScalarType::F32,
            "double" | "float64" => ScalarType::F64,
            _ => return None,
        })
    }

    /// The classic PLY name.
    pub fn name(self) -> &'static str {
        match self {
            ScalarType::I8 => "char",
            ScalarType::U8 => "uchar",
            ScalarType::I16 => "short",
            ScalarType::U16 => "ushort",
            ScalarType::I32 => "int",
            ScalarType::U32 => "uint",
            ScalarType::F32 => "float",
            ScalarType::F64 => "double",
        }
    }

    /// Bytes per value in binary files.
    pub fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::F64 => 8,
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, ScalarType::F32 | ScalarType::F64)
    }
}

/// The type of one property.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PropertyType {
    /// One value per element instance.
    Scalar(ScalarType),
    /// A count of type `count`, then that many values of type `item`.
    List { count: ScalarType, item: ScalarType },
}

/// A property declared in the header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PropertyDef {
    pub name: String,
    pub ty: PropertyType,
}

/// An element declared in the header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ElementDef {
    pub name: String,
    pub count: usize,
    pub properties: Vec<PropertyDef>,
}

/// The parsed header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlyHeader {
    pub format: PlyFormat,
    pub elements: Vec<ElementDef>,
    /// `comment` and `obj_info` lines, without the keyword.
    pub comments: Vec<String>,
}

/// Values of one scalar column (or the items of one list column), in the file's type.
macro_rules! values_enum {
    ($($var:ident($t:ty)),* $(,)?) => {
        /// A column of values in the property's own type.
        #[derive(Debug, Clone, PartialEq)]
        pub enum Values { $($var(Vec<$t>)),* }

        impl Values {
            fn with_capacity(ty: ScalarType, cap: usize) -> Values {
                match ty { $(ScalarType::$var => Values::$var(Vec::with_capacity(cap))),* }
            }

            /// Number of values.
            pub fn len(&self) -> usize {
                match self { $(Values::$var(v) => v.len()),* }
            }

            /// Whether there are none.
            pub fn is_empty(&self) -> bool {
                self.len() == 0
            }

            /// The type the file declared.
            pub fn scalar_type(&self) -> ScalarType {
                match self { $(Values::$var(_) => ScalarType::$var),* }
            }

            /// Value `i` widened to f64 (exact for every PLY type).
            pub fn get(&self, i: usize) -> Option<f64> {
                match self { $(Values::$var(v) => v.get(i).map(|x| f64::from(*x))),* }
            }

            /// Appends one little-endian value; false when `bytes` has the wrong length.
            fn push_le(&mut self, bytes: &[u8]) -> bool {
                match self {
                    $(Values::$var(v) => match bytes.try_into() {
                        Ok(raw) => { v.push(<$t>::from_le_bytes(raw)); true }
                        Err(_) => false,
                    }),*
                }
            }

            /// Appends one value parsed from ASCII text; false when it does not parse.
            fn push_text(&mut self, token: &str) -> bool {
                match self {
                    $(Values::$var(v) => match token.parse::<$t>() {
                        Ok(x) => { v.push(x); true }
                        Err(_) => false,
                    }),*
                }
            }
        }
    };
}

values_enum!(
    I8(i8),
    U8(u8),
    I16(i16),
    U16(u16),
    I32(i32),
    U32(u32),
    F32(f32),
    F64(f64)
);

impl Values {
    /// Value `i` as f32: exact for `float` columns (so finite values round-trip bit for
    /// bit), rounded to nearest for `double` and wide integer columns.
    pub fn get_f32(&self, i: usize) -> Option<f32> {
        match self {
            Values::F32(v) => v.get(i).copied(),
            #[allow(clippy::cast_possible_truncation)]
            Values::F64(v) => v.get(i).map(|x| *x as f32),
            other => other.get(i).map(|x| x as f32),
        }
    }
}

/// The data of one property.
#[derive(Debug, Clone, PartialEq)]
pub enum Column {
    /// One value per element instance.
    Scalar(Values),
    /// Instance `i` owns `items[offsets[i]..offsets[i + 1]]`.
    List { offsets: Vec<usize>, items: Values },
}

impl Column {
    fn new(ty: PropertyType, cap: usize) -> Column {
        match ty {
            PropertyType::Scalar(s) => Column::Scalar(Values::with_capacity(s, cap)),
            PropertyType::List { item, .. } => {
                let mut offsets = Vec::with_capacity(cap.saturating_add(1));
                offsets.push(0);
                Column::List {
                    offsets,
                    items: Values::with_capacity(item, cap),
                }
            }
        }
    }
}

/// One element with its data, columns parallel to `def.properties`.
#[derive(Debug, Clone, PartialEq)]
pub struct Element {
    pub def: ElementDef,
    pub columns: Vec<Column>,
}

impl Element {
    /// The column of a property by name.
    pub fn column(&self, name: &str) -> Option<&Column> {
        let i = self.def.properties.iter().position(|p| p.name == name)?;
        self.columns.get(i)
    }

    /// The values of a scalar property by name (`None` if absent or a list).
    pub fn scalar(&self, name: &str) -> Option<&Values> {
        match self.column(name)? {
            Column::Scalar(v) => Some(v),
            Column::List { .. } => None,
        }
    }

    /// Number of instances.
    pub fn len(&self) -> usize {
        self.def.count
    }

    /// Whether the element has no instances.
    pub fn is_empty(&self) -> bool {
        self.def.count == 0
    }
}

/// A parsed PLY file.
#[derive(Debug, Clone, PartialEq)]
pub struct PlyData {
    pub header: PlyHeader,
    pub elements: Vec<Element>,
}

impl PlyData {
    /// An element by name.
    pub fn element(&self, name: &str) -> Option<&Element> {
        self.elements.iter().find(|e| e.def.name == name)
    }
}

/// Reads and parses a PLY file.
pub fn read_ply(path: impl AsRef<Path>) -> Result<PlyData> {
    let path = path.as_ref();
    parse_ply(&read_bytes(path)?, &show(path))
}

/// Parses PLY bytes; `label` names the file in errors.
pub fn parse_ply(bytes: &[u8], label: &str) -> Result<PlyData> {
    let (header, body_start) = parse_header(bytes, label)?;
    let body = bytes.get(body_start..).unwrap_or_default();
    let elements = match header.format {
        PlyFormat::BinaryLittleEndian => parse_binary_body(&header, body, label)?,
        PlyFormat::Ascii => {
            // Body errors cite file line numbers, so count the header's lines.
            let head = bytes.get(..body_start).unwrap_or_default();
            let header_lines = head.iter().filter(|b| **b == b'\n').count();
            parse_ascii_body(&header, body, header_lines, label)?
        }
    };
    Ok(PlyData { header, elements })
}

/// Parses the header; returns it and the byte offset where the body starts.
pub fn parse_header(bytes: &[u8], label: &str) -> Result<(PlyHeader, usize)> {
    let mut lines = HeaderLines {
        bytes,
        pos: 0,
        line: 0,
    };
    let first = lines.next_line(label)?;
    if first != "ply" {
        return Err(header_err(
            label,
            format!("line 1 is {first:?}, expected \"ply\" (not a PLY file)"),
        ));
    }
    let mut format = None;
    let mut elements: Vec<ElementDef> = Vec::new();
    let mut comments = Vec::new();
    loop {
        let text = lines.next_line(label)?;
        let line = lines.line;
        let mut words = text.split_ascii_whitespace();
        let keyword = words.next().unwrap_or_default();
        let at = |detail: String| header_err(label, format!("line {line}: {detail}"));
        match keyword {
            "end_header" => break,
            "comment" | "obj_info" => {
                let rest = text.trim_start().get(keyword.len()..).unwrap_or_default();
                comments.push(rest.trim().to_string());
            }
            "format" => format = Some(parse_format_line(&mut words, label, line)?),
            "element" => {
                let (Some(name), Some(count), None) = (words.next(), words.next(), words.next())
                else {
                    return Err(at(format!("{text:?}, expected \"element NAME COUNT\"")));
                };
                let count = count.parse::<usize>().map_err(|_| {
                    at(format!(
                        "element `{name}` count {count:?}, expected a non-negative integer"
                    ))
                })?;
                if elements.iter().any(|e| e.name == name) {
                    return Err(at(format!("element `{name}` declared twice")));
                }
                elements.push(ElementDef {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(at("`property` before any `element`".to_string()));
                };
                let prop = parse_property_line(&text, &mut words).map_err(at)?;
                if element.properties.iter().any(|p| p.name == prop.name) {
                    return Err(at(format!(
                        "property `{}` declared twice in element `{}`",
                        prop.name, element.name
                    )));
                }
                element.properties.push(prop);
            }
            "" => {}
            other => return Err(at(format!("unknown keyword {other:?}"))),
        }
    }
    let format = format.ok_or_else(|| header_err(label, "no `format` line before `end_header`"))?;
    Ok((
        PlyHeader {
            format,
            elements,
            comments,
        },
        lines.pos,
    ))
}

fn parse_format_line<'a>(
    words: &mut impl Iterator<Item = &'a str>,
    label: &str,
    line: usize,
) -> Result<PlyFormat> {
    let (name, version) = (
        words.next().unwrap_or_default(),
        words.next().unwrap_or_default(),
    );
    let format = match name {
        "ascii" => PlyFormat::Ascii,
        "binary_little_endian" => PlyFormat::BinaryLittleEndian,
        "binary_big_endian" => {
            return Err(unsupported(
                label,
                "PLY format",
                "binary_big_endian (only binary_little_endian and ascii are read; convert the file, e.g. with plyfile or meshlab)",
            ))
        }
        other => {
            return Err(header_err(
                label,
                format!("line {line}: format {other:?}, expected ascii or binary_little_endian"),
            ))
        }
    };
    if version != "1.0" {
        return Err(header_err(
            label,
            format!("line {line}: format version {version:?}, expected \"1.0\""),
        ));
    }
    Ok(format)
}

fn parse_property_line<'a>(
    text: &str,
    words: &mut impl Iterator<Item = &'a str>,
) -> Result<PropertyDef, String> {
    let bad_type = |t: &str| {
        format!("unknown property type {t:?} (expected char, uchar, short, ushort, int, uint, float, double or their sized names)")
    };
    match words.next() {
        Some("list") => {
            let (Some(count), Some(item), Some(name), None) =
                (words.next(), words.next(), words.next(), words.next())
            else {
                return Err(format!(
                    "{text:?}, expected \"property list COUNT_TYPE ITEM_TYPE NAME\""
                ));
            };
            let count_ty = ScalarType::parse(count).ok_or_else(|| bad_type(count))?;
            let item_ty = ScalarType::parse(item).ok_or_else(|| bad_type(item))?;
            if !count_ty.is_integer() {
                return Err(format!(
                    "list `{name}` has count type {count}, expected an integer type"
                ));
            }
            Ok(PropertyDef {
                name: name.to_string(),
                ty: PropertyType::List {
                    count: count_ty,
                    item: item_ty,
                },
            })
        }
        Some(ty) => {
            let (Some(name), None) = (words.next(), words.next()) else {
                return Err(format!("{text:?}, expected \"property TYPE NAME\""));
            };
            let ty = ScalarType::parse(ty).ok_or_else(|| bad_type(ty))?;
            Ok(PropertyDef {
                name: name.to_string(),
                ty: PropertyType::Scalar(ty),
            })
        }
        None => Err("`property` without a type and name".to_string()),
    }
}

/// Header lines, `\n`-terminated (a trailing `\r` is dropped), counted from 1.
struct HeaderLines<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
}

impl HeaderLines<'_> {
    fn next_line(&mut self, label: &str) -> Result<String> {
        let rest = self.bytes.get(self.pos..).unwrap_or_default();
        let Some(len) = rest.iter().position(|b| *b == b'\n') else {
            return Err(if self.line == 0 {
                header_err(label, "no header line (empty file or not a PLY file)")
            } else {
                header_err(label, "the header ends without `end_header`")
            });
        };
        let raw = rest.get(..len).unwrap_or_default();
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        self.pos += len + 1;
        self.line += 1;
        match std::str::from_utf8(raw) {
            Ok(s) if s.is_ascii() => Ok(s.to_string()),
            _ => Err(header_err(
                label,
                format!(
                    "line {}: not ASCII text (binary data before `end_header`?)",
                    self.line
                ),
            )),
        }
    }
}

/// A cursor over the binary body; errors name the element, instance and property.
struct BinaryCursor<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> BinaryCursor<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let slice = self.bytes.get(self.pos..end)?;
        self.pos = end;
        Some(slice)
    }
}

fn parse_binary_body(header: &PlyHeader, body: &[u8], label: &str) -> Result<Vec<Element>> {
    let mut cursor = BinaryCursor {
        bytes: body,
        pos: 0,
    };
    header
        .elements
        .iter()
        .map(|def| parse_binary_element(def, &mut cursor, label))
        .collect()
}

fn fixed_row_size(def: &ElementDef) -> Option<usize> {
    def.properties.iter().try_fold(0usize, |acc, p| match p.ty {
        PropertyType::Scalar(s) => acc.checked_add(s.size()),
        PropertyType::List { .. } => None,
    })
}

fn parse_binary_element(
    def: &ElementDef,
    cursor: &mut BinaryCursor<'_>,
    label: &str,
) -> Result<Element> {
    let remaining = cursor.bytes.len().saturating_sub(cursor.pos);
    if let Some(stride) = fixed_row_size(def) {
        // Fixed-size rows: check the whole element fits before allocating for it.
        let fits = def
            .count
            .checked_mul(stride)
            .is_some_and(|need| need <= remaining);
        if !fits {
            return Err(binary_truncation(def, stride, remaining, label));
        }
    }
    // A list row is at least its count's size: never reserve more rows than bytes left.
    let cap = def.count.min(remaining);
    let mut columns: Vec<Column> = def
        .properties
        .iter()
        .map(|p| Column::new(p.ty, cap))
        .collect();
    for row in 0..def.count {
        for (prop, column) in def.properties.iter().zip(columns.iter_mut()) {
            let cut_off = || {
                truncated(
                    label,
                    format!("element `{}` instance {row} of {}: property `{}` runs past the end of the file", def.name, def.count, prop.name),
                )
            };
            match read_binary_value(prop, column, cursor) {
                Ok(true) => {}
                Ok(false) => return Err(cut_off()),
                Err(count) => {
                    return Err(invalid(
                        label,
                        format!(
                            "element `{}` instance {row} list property `{}`",
                            def.name, prop.name
                        ),
                        format!("list count {count} is not a non-negative integer"),
                    ))
                }
            }
        }
    }
    Ok(Element {
        def: def.clone(),
        columns,
    })
}

/// Reads one value (or one list) into its column. `Ok(false)` = out of bytes;
/// `Err(count)` = a list count that is negative.
fn read_binary_value(
    prop: &PropertyDef,
    column: &mut Column,
    cursor: &mut BinaryCursor<'_>,
) -> Result<bool, f64> {
    match (prop.ty, column) {
        (PropertyType::Scalar(s), Column::Scalar(values)) => Ok(cursor
            .take(s.size())
            .is_some_and(|bytes| values.push_le(bytes))),
        (PropertyType::List { count, item }, Column::List { offsets, items }) => {
            let mut count_values = Values::with_capacity(count, 1);
            if !cursor
                .take(count.size())
                .is_some_and(|bytes| count_values.push_le(bytes))
            {
                return Ok(false);
            }
            let raw = count_values.get(0).unwrap_or(-1.0);
            let n = list_len(raw).ok_or(raw)?;
            let Some(bytes) = n.checked_mul(item.size()).and_then(|len| cursor.take(len)) else {
                return Ok(false);
            };
            for chunk in bytes.chunks_exact(item.size()) {
                items.push_le(chunk);
            }
            offsets.push(items.len());
            Ok(true)
        }
        // Columns are built from the same property list, so the kinds always agree.
        _ => Ok(true),
    }
}

fn list_len(count: f64) -> Option<usize> {
    if count >= 0.0 && count.fract() == 0.0 && count <= usize::MAX as f64 {
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        Some(count as usize)
    } else {
        None
    }
}

/// Names the first instance and property that do not fit in the remaining bytes.
fn binary_truncation(
    def: &ElementDef,
    stride: usize,
    remaining: usize,
    label: &str,
) -> crate::error::SceneError {
    let row = remaining / stride.max(1);
    let mut offset = row * stride;
    let mut property = def.properties.first().map_or("", |p| p.name.as_str());
    for p in &def.properties {
        property = p.name.as_str();
        let PropertyType::Scalar(s) = p.ty else { break };
        if offset + s.size() > remaining {
            break;
        }
        offset += s.size();
    }
    truncated(
        label,
        format!(
            "element `{}` declares {} instances of {stride} bytes but the file holds {remaining} bytes for it: instance {row}, property `{property}` is cut off",
            def.name, def.count
        ),
    )
}

fn parse_ascii_body(
    header: &PlyHeader,
    body: &[u8],
    header_lines: usize,
    label: &str,
) -> Result<Vec<Element>> {
    let text = std::str::from_utf8(body).map_err(|e| {
        invalid(
            label,
            "ascii body",
            format!(
                "not ASCII text (bad byte at body offset {})",
                e.valid_up_to()
            ),
        )
    })?;
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1 + header_lines, l))
        .filter(|(_, l)| !l.trim().is_empty());
    let mut elements = Vec::with_capacity(header.elements.len());
    for def in &header.elements {
        let cap = def.count.min(body.len());
        let mut columns: Vec<Column> = def
            .properties
            .iter()
            .map(|p| Column::new(p.ty, cap))
            .collect();
        for row in 0..def.count {
            let Some((line_no, line)) = lines.next() else {
                return Err(truncated(
                    label,
                    format!(
                        "element `{}` declares {} instances but the file ends after {row}",
                        def.name, def.count
                    ),
                ));
            };
            parse_ascii_row(def, &mut columns, line, line_no, label)?;
        }
        elements.push(Element {
            def: def.clone(),
            columns,
        });
    }
    Ok(elements)
}

fn parse_ascii_row(
    def: &ElementDef,
    columns: &mut [Column],
    line: &str,
    line_no: usize,
    label: &str,
) -> Result<()> {
    let mut tokens = line.split_ascii_whitespace();
    for (prop, column) in def.properties.iter().zip(columns.iter_mut()) {
        let field = || format!("element `{}` property `{}`", def.name, prop.name);
        let mut next = |expected: ScalarType| {
            tokens.next().ok_or_else(|| {
                parse_err(
                    label,
                    line_no,
                    field(),
                    format!("a {} value", expected.name()),
                    "end of line",
                )
            })
        };
        match (prop.ty, column) {
            (PropertyType::Scalar(s), Column::Scalar(values)) => {
                let token = next(s)?;
                if !values.push_text(token) {
                    return Err(parse_err(
                        label,
                        line_no,
                        field(),
                        format!("a {} value", s.name()),
                        token,
                    ));
                }
            }
            (PropertyType::List { count, item }, Column::List { offsets, items }) => {
                let token = next(count)?;
                let n = token.parse::<usize>().map_err(|_| {
                    parse_err(label, line_no, field(), "a non-negative list count", token)
                })?;
                for _ in 0..n {
                    let token = next(item)?;
                    if !items.push_text(token) {
                        return Err(parse_err(
                            label,
                            line_no,
                            field(),
                            format!("a {} list item", item.name()),
                            token,
                        ));
                    }
                }
                offsets.push(items.len());
            }
            _ => {}
        }
    }
    match tokens.next() {
        None => Ok(()),
        Some(extra) => Err(parse_err(
            label,
            line_no,
            format!("element `{}`", def.name),
            format!("{} properties on the line", def.properties.len()),
            format!("extra token {extra}"),
        )),
    }
}
