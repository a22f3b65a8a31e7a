//! The value tree a pickle is read into: [`PyValue`], [`DType`] and [`NdArray`].

use std::fmt;

/// A Python value as read from a pickle.
#[derive(Debug, Clone, PartialEq)]
pub enum PyValue {
    None,
    Bool(bool),
    /// Python ints that fit in 64 bits; wider ones are an error.
    Int(i64),
    Float(f64),
    Str(String),
    /// `bytes` and `bytearray`.
    Bytes(Vec<u8>),
    List(Vec<PyValue>),
    Tuple(Vec<PyValue>),
    /// Keys in insertion order, as Python keeps them. A key written twice keeps its first position
    /// and its last value, as Python's `dict` would.
    Dict(Vec<(PyValue, PyValue)>),
    /// A numpy array; numpy scalars (`np.float32(1.5)`) are 0-dimensional arrays (`shape == []`).
    NdArray(NdArray),
    /// A bare numpy dtype object (pickled on its own, not as part of an array).
    DType(DType),
}

impl PyValue {
    /// Python's name for the value's type, for error messages.
    pub fn type_name(&self) -> &'static str {
        match self {
            PyValue::None => "None",
            PyValue::Bool(_) => "bool",
            PyValue::Int(_) => "int",
            PyValue::Float(_) => "float",
            PyValue::Str(_) => "str",
            PyValue::Bytes(_) => "bytes",
            PyValue::List(_) => "list",
            PyValue::Tuple(_) => "tuple",
            PyValue::Dict(_) => "dict",
            PyValue::NdArray(_) => "numpy.ndarray",
            PyValue::DType(_) => "numpy.dtype",
        }
    }

    /// The value under the string key `key`, if this is a dict that has it.
    pub fn get(&self, key: &str) -> Option<&PyValue> {
        match self {
            PyValue::Dict(pairs) => pairs.iter().find_map(|(k, v)| match k {
                PyValue::Str(s) if s == key => Some(v),
                _ => None,
            }),
            _ => None,
        }
    }
}

/// The numpy element types this reader understands. Data is always held little-endian.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DType {
    Bool,
    Int8,
    Int16,
    Int32,
    Int64,
    UInt8,
    UInt16,
    UInt32,
    UInt64,
    Float32,
    Float64,
}

impl DType {
    /// numpy's `dtype.name`, e.g. `"float32"`.
    pub fn name(self) -> &'static str {
        match self {
            DType::Bool => "bool",
            DType::Int8 => "int8",
            DType::Int16 => "int16",
            DType::Int32 => "int32",
            DType::Int64 => "int64",
            DType::UInt8 => "uint8",
            DType::UInt16 => "uint16",
            DType::UInt32 => "uint32",
            DType::UInt64 => "uint64",
            DType::Float32 => "float32",
            DType::Float64 => "float64",
        }
    }

    /// numpy's `dtype.str` of the little-endian form, e.g. `"<f4"` or `"|b1"`.
    pub fn descr(self) -> &'static str {
        match self {
            DType::Bool => "|b1",
            DType::Int8 => "|i1",
            DType::Int16 => "<i2",
            DType::Int32 => "<i4",
            DType::Int64 => "<i8",
            DType::UInt8 => "|u1",
            DType::UInt16 => "<u2",
            DType::UInt32 => "<u4",
            DType::UInt64 => "<u8",
            DType::Float32 => "<f4",
            DType::Float64 => "<f8",
        }
    }

    /// Bytes per element.
    pub fn itemsize(self) -> usize {
        match self {
            DType::Bool | DType::Int8 | DType::UInt8 => 1,
            DType::Int16 | DType::UInt16 => 2,
            DType::Int32 | DType::UInt32 | DType::Float32 => 4,
            DType::Int64 | DType::UInt64 | DType::Float64 => 8,
        }
    }

    /// Parses numpy's type code without byte order (`"f4"`, `"b1"`, `"O8"`), as `numpy.dtype` is
    /// called in pickles. The error says why a known-but-unsupported code is refused.
    pub(super) fn from_code(code: &str) -> Result<DType, String> {
        let mut chars = code.chars();
        let kind = chars.next().ok_or_else(|| "empty type code".to_string())?;
        let size: Option<usize> = chars.as_str().parse().ok();
        let dtype = match (kind, size) {
            ('b', Some(1)) => DType::Bool,
            ('i', Some(1)) => DType::Int8,
            ('i', Some(2)) => DType::Int16,
            ('i', Some(4)) => DType::Int32,
            ('i', Some(8)) => DType::Int64,
            ('u', Some(1)) => DType::UInt8,
            ('u', Some(2)) => DType::UInt16,
            ('u', Some(4)) => DType::UInt32,
            ('u', Some(8)) => DType::UInt64,
            ('f', Some(4)) => DType::Float32,
            ('f', Some(8)) => DType::Float64,
            ('O', _) => {
                return Err("object arrays are not supported (their elements are arbitrary \
                            Python objects)"
                    .into())
            }
            ('f', _) => return Err("only float32 and float64 are supported".into()),
            ('c', _) => return Err("complex dtypes are not supported".into()),
            ('U' | 'S' | 'a', _) => return Err("string dtypes are not supported".into()),
            ('V', _) => return Err("structured (void) dtypes are not supported".into()),
            ('M' | 'm', _) => return Err("datetime dtypes are not supported".into()),
            _ => return Err("unknown type code".into()),
        };
        Ok(dtype)
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A numpy array. `data` holds the elements little-endian, `product(shape) * itemsize` bytes, in
/// C (row-major) order, or in Fortran (column-major) order when `fortran_order` is set, as the
/// file stored it; [`NdArray::to_c_order`] gives the row-major form.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    pub dtype: DType,
    pub shape: Vec<usize>,
    pub fortran_order: bool,
    pub data: Vec<u8>,
}

impl NdArray {
    /// Number of elements (1 for a 0-dimensional array).
    pub fn num_elements(&self) -> usize {
        // Saturating: arrays from `parse` are always consistent, but the fields are public.
        self.shape.iter().fold(1usize, |n, &d| n.saturating_mul(d))
    }

    /// The same array with its data in C order (a copy).
    ///
    /// An array whose `data` does not hold exactly `product(shape) * itemsize` bytes (only possible
    /// if built by hand) is returned unchanged.
    pub fn to_c_order(&self) -> NdArray {
        if !self.fortran_order {
            return self.clone();
        }
        // Fortran-order data of shape S is C-order data of shape reverse(S); reversing the axes
        // of that gives shape S in C order.
        let reversed: Vec<usize> = self.shape.iter().rev().copied().collect();
        let axes: Vec<usize> = (0..self.shape.len()).rev().collect();
        match permute_axes(&self.data, self.dtype.itemsize(), &reversed, &axes) {
            Some(data) => {
                NdArray { dtype: self.dtype, shape: self.shape.clone(), fortran_order: false, data }
            }
            None => self.clone(),
        }
    }

    /// The elements as `f32`, in C order, for float32 and float64 arrays (float64 is rounded to
    /// the nearest `f32`, as numpy's `astype(np.float32)` does). `None` for other dtypes.
    pub fn to_f32_vec(&self) -> Option<Vec<f32>> {
        let c = self.to_c_order();
        match self.dtype {
            DType::Float32 => Some(chunks::<4>(&c.data).map(f32::from_le_bytes).collect()),
            DType::Float64 => {
                Some(chunks::<8>(&c.data).map(|b| f64::from_le_bytes(b) as f32).collect())
            }
            _ => None,
        }
    }

    /// The elements as `f64`, in C order, for any dtype (bool is 0 or 1; 64-bit integers beyond
    /// 2^53 are rounded).
    pub fn to_f64_vec(&self) -> Vec<f64> {
        let c = self.to_c_order();
        let d = &c.data;
        match self.dtype {
            DType::Bool => d.iter().map(|&b| f64::from(u8::from(b != 0))).collect(),
            DType::Int8 => d.iter().map(|&b| f64::from(b as i8)).collect(),
            DType::UInt8 => d.iter().map(|&b| f64::from(b)).collect(),
            DType::Int16 => chunks::<2>(d).map(|b| f64::from(i16::from_le_bytes(b))).collect(),
            DType::UInt16 => chunks::<2>(d).map(|b| f64::from(u16::from_le_bytes(b))).collect(),
            DType::Int32 => chunks::<4>(d).map(|b| f64::from(i32::from_le_bytes(b))).collect(),
            DType::UInt32 => chunks::<4>(d).map(|b| f64::from(u32::from_le_bytes(b))).collect(),
            DType::Int64 => chunks::<8>(d).map(|b| i64::from_le_bytes(b) as f64).collect(),
            DType::UInt64 => chunks::<8>(d).map(|b| u64::from_le_bytes(b) as f64).collect(),
            DType::Float32 => chunks::<4>(d).map(|b| f64::from(f32::from_le_bytes(b))).collect(),
            DType::Float64 => chunks::<8>(d).map(f64::from_le_bytes).collect(),
        }
    }
}

/// Fixed-size little-endian chunks of `data` (a trailing partial chunk is ignored; arrays from
/// `parse` never have one).
fn chunks<const N: usize>(data: &[u8]) -> impl Iterator<Item = [u8; N]> + '_ {
    data.chunks_exact(N).filter_map(|c| <[u8; N]>::try_from(c).ok())
}

/// Transposes C-order data of shape `shape` by `axes` (numpy's `transpose(axes)`), returning the
/// result in C order. `None` if the data length, shape and axes are inconsistent.
pub(super) fn permute_axes(
    data: &[u8],
    itemsize: usize,
    shape: &[usize],
    axes: &[usize],
) -> Option<Vec<u8>> {
    let n = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d))?;
    if axes.len() != shape.len() || n.checked_mul(itemsize)? != data.len() {
        return None;
    }
    let mut seen = vec![false; shape.len()];
    for &a in axes {
        let slot = seen.get_mut(a)?;
        if *slot {
            return None;
        }
        *slot = true;
    }
    // Element strides of the input, in C order.
    let mut in_strides = vec![0usize; shape.len()];
    let mut s = 1usize;
    for (stride, &dim) in in_strides.iter_mut().zip(shape).rev() {
        *stride = s;
        s = s.checked_mul(dim)?;
    }
    let out_shape: Vec<usize> =
        axes.iter().map(|&a| shape.get(a).copied()).collect::<Option<_>>()?;
    let out_strides: Vec<usize> =
        axes.iter().map(|&a| in_strides.get(a).copied()).collect::<Option<_>>()?;

    let mut out = Vec::with_capacity(data.len());
    let mut index = vec![0usize; out_shape.len()];
    let mut offset = 0usize; // element offset into the input of the current output element
    for _ in 0..n {
        let start = offset.checked_mul(itemsize)?;
        out.extend_from_slice(data.get(start..start.checked_add(itemsize)?)?);
        // Odometer step over the output index, last axis fastest.
        for k in (0..out_shape.len()).rev() {
            let (i, dim, stride) = (index.get_mut(k)?, *out_shape.get(k)?, *out_strides.get(k)?);
            *i += 1;
            offset += stride;
            if *i < dim {
                break;
            }
            offset -= stride * dim;
            *i = 0;
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn permute_matches_numpy_transpose() {
        // np.arange(6).reshape(2, 3).T -> [[0, 3], [1, 4], [2, 5]]
        let data: Vec<u8> = (0u8..6).collect();
        assert_eq!(permute_axes(&data, 1, &[2, 3], &[1, 0]), Some(vec![0, 3, 1, 4, 2, 5]));
        // Not a permutation.
        assert_eq!(permute_axes(&data, 1, &[2, 3], &[0, 0]), None);
        assert_eq!(permute_axes(&data, 1, &[2, 3], &[0, 5]), None);
        // Fortran-order (2, 3): memory [a00, a10, a01, a11, a02, a12].
        let f = NdArray { dtype: DType::UInt8, shape: vec![2, 3], fortran_order: true, data };
        assert_eq!(f.to_c_order().data, vec![0, 2, 4, 1, 3, 5]);
    }

    #[test]
    fn hand_built_arrays_never_panic() {
        let odd = NdArray {
            dtype: DType::Float32,
            shape: vec![3, 3],
            fortran_order: true,
            data: vec![1, 2, 3],
        };
        assert_eq!(odd.to_c_order(), odd);
        assert_eq!(odd.to_f32_vec(), Some(vec![]));
        let huge = NdArray {
            dtype: DType::Float64,
            shape: vec![usize::MAX, 4],
            fortran_order: true,
            data: vec![],
        };
        assert_eq!(huge.num_elements(), usize::MAX);
        assert_eq!(huge.to_c_order(), huge);
    }
}
