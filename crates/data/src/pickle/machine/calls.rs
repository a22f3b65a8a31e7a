//! The callables a numpy pickle may name, re-implemented (numpy's array and dtype constructors,
//! `_frombuffer`, `_codecs.encode`, `bytes`), and the BUILD states of arrays and dtypes.

use super::{clip, Machine};
use crate::pickle::arena::{ByteOrder, Callable, Obj, Res, Val};
use crate::pickle::value::permute_axes;
use crate::pickle::{DType, NdArray};

impl Machine<'_> {
    fn shape_of(&self, v: Val) -> Res<Vec<usize>> {
        self.tuple_of(v, "array shape")?
            .iter()
            .map(|&d| match d {
                Val::Int(n) => usize::try_from(n)
                    .map_err(|_| self.invalid(format!("negative array dimension {n}"))),
                other => Err(self
                    .invalid(format!("array dimensions must be ints, got {}", self.kind(other)))),
            })
            .collect()
    }

    fn dtype_of(&self, v: Val) -> Res<(DType, ByteOrder)> {
        match self.obj(v) {
            Some(Obj::Dtype { dtype, order, code }) => match order {
                Some(o) => Ok((*dtype, *o)),
                None if dtype.itemsize() == 1 => Ok((*dtype, ByteOrder::NotApplicable)),
                // numpy always pickles a dtype's byte order in its BUILD state; without it the
                // bytes could be either.
                None => Err(self.invalid(format!(
                    "numpy.dtype('{code}') has no byte order (its BUILD state is missing)"
                ))),
            },
            _ => Err(self.invalid(format!("expected a numpy.dtype, got {}", self.kind(v)))),
        }
    }

    /// The re-implementation of each allowed callable.
    pub(super) fn call(&mut self, callable: Callable, args: &[Val]) -> Res<Val> {
        let wrong_args = |m: &Self| {
            m.invalid(format!("{}: unexpected arguments ({} given)", callable.name(), args.len()))
        };
        match callable {
            Callable::NdarrayType => Err(self
                .invalid("numpy.ndarray can only be passed to _reconstruct, not called directly")),
            Callable::Reconstruct => {
                let [class, _shape, _typecode] = args else { return Err(wrong_args(self)) };
                // The shape and type code are placeholders that BUILD overwrites; the class must
                // be ndarray itself (subclasses such as np.matrix would need their own code).
                match self.obj(*class) {
                    Some(Obj::Callable(Callable::NdarrayType)) => {
                        Ok(self.new_obj(Obj::PendingArray))
                    }
                    _ => Err(self.invalid(format!(
                        "_reconstruct of {} (only numpy.ndarray is supported)",
                        self.kind(*class)
                    ))),
                }
            }
            Callable::Dtype => {
                // numpy passes (code, align, copy); align and copy do not change the data.
                let Some(code_v) = args.first().filter(|_| args.len() <= 3) else {
                    return Err(wrong_args(self));
                };
                let code = clip(self.str_of(*code_v, "numpy.dtype type code")?);
                let (order, bare) = match code.as_bytes().first() {
                    Some(b'<') => (Some(ByteOrder::Little), code.get(1..)),
                    Some(b'>') => (Some(ByteOrder::Big), code.get(1..)),
                    Some(b'|') => (Some(ByteOrder::NotApplicable), code.get(1..)),
                    _ => (None, Some(code.as_str())),
                };
                let dtype = DType::from_code(bare.unwrap_or_default())
                    .map_err(|why| self.invalid(format!("numpy.dtype('{code}'): {why}")))?;
                Ok(self.new_obj(Obj::Dtype { dtype, order, code }))
            }
            Callable::Scalar => {
                let [dtype_v, data_v] = args else { return Err(wrong_args(self)) };
                let (dtype, order) = self.dtype_of(*dtype_v)?;
                let array = self.make_array(dtype, order, Vec::new(), false, *data_v)?;
                Ok(self.new_obj(Obj::Array(array)))
            }
            Callable::FromBuffer => self.call_frombuffer(args),
            Callable::CodecsEncode => {
                let [text_v, encoding_v] = args else { return Err(wrong_args(self)) };
                let encoding = self.str_of(*encoding_v, "_codecs.encode encoding")?;
                if encoding != "latin1" && encoding != "latin-1" {
                    return Err(self.invalid(format!(
                        "_codecs.encode with encoding '{}' (only latin1, as pickle writes bytes)",
                        clip(encoding)
                    )));
                }
                let text = self.str_of(*text_v, "_codecs.encode text")?;
                let out: Option<Vec<u8>> = text.chars().map(|c| u8::try_from(c).ok()).collect();
                let out = out.ok_or_else(|| {
                    self.invalid("_codecs.encode: text has characters beyond latin1")
                })?;
                self.charge(out.len())?;
                Ok(self.new_obj(Obj::Bytes(out)))
            }
            Callable::Bytes => {
                if !args.is_empty() {
                    return Err(self.invalid(
                        "builtins.bytes is only accepted with no arguments (protocol 2's b'')",
                    ));
                }
                Ok(self.new_obj(Obj::Bytes(Vec::new())))
            }
        }
    }

    /// `_frombuffer(buffer, dtype, shape, order[, axis_order])`, numpy's protocol-5 form:
    /// `frombuffer(buffer, dtype).reshape(shape, order=order)`, or with order 'K' the C-order
    /// buffer transposed by `axis_order`.
    fn call_frombuffer(&mut self, args: &[Val]) -> Res<Val> {
        let (buf_v, dtype_v, shape_v, order_v, axes_v) = match args {
            [b, d, s, o] => (*b, *d, *s, *o, None),
            [b, d, s, o, a] => (*b, *d, *s, *o, Some(*a)),
            _ => {
                return Err(self
                    .invalid(format!("_frombuffer: unexpected arguments ({} given)", args.len())))
            }
        };
        let (dtype, byte_order) = self.dtype_of(dtype_v)?;
        let shape = self.shape_of(shape_v)?;
        let order = self.str_of(order_v, "_frombuffer order")?.to_owned();
        let axes = match axes_v {
            Some(Val::None) | None => None,
            Some(a) => Some(self.shape_of(a)?),
        };
        let array = match (order.as_str(), axes) {
            ("C", None) => self.make_array(dtype, byte_order, shape, false, buf_v)?,
            ("F", None) => self.make_array(dtype, byte_order, shape, true, buf_v)?,
            ("K", Some(axes)) => {
                let c = self.make_array(dtype, byte_order, shape.clone(), false, buf_v)?;
                self.charge(c.data.len())?;
                let data =
                    permute_axes(&c.data, dtype.itemsize(), &shape, &axes).ok_or_else(|| {
                        self.invalid(format!(
                            "_frombuffer: axis order {axes:?} is not a permutation of the {} axes",
                            shape.len()
                        ))
                    })?;
                let out_shape = axes.iter().filter_map(|&a| shape.get(a).copied()).collect();
                NdArray { dtype, shape: out_shape, fortran_order: false, data }
            }
            _ => {
                return Err(self.invalid(format!(
                    "_frombuffer: order '{}' (expected 'C', 'F', or 'K' with an axis order)",
                    clip(&order)
                )))
            }
        };
        Ok(self.new_obj(Obj::Array(array)))
    }

    /// An array holding a copy of the bytes object `data_v`, after checking its size against the
    /// shape; big-endian data is converted to little-endian.
    fn make_array(
        &mut self,
        dtype: DType,
        order: ByteOrder,
        shape: Vec<usize>,
        fortran_order: bool,
        data_v: Val,
    ) -> Res<NdArray> {
        let len = self.bytes_of(data_v, "array data")?.len();
        let expected = shape
            .iter()
            .try_fold(dtype.itemsize(), |n, &d| n.checked_mul(d))
            .ok_or_else(|| self.invalid(format!("array shape {shape:?} overflows")))?;
        if expected != len {
            return Err(self.invalid(format!(
                "array of shape {shape:?} and dtype {dtype} needs {expected} bytes, got {len}"
            )));
        }
        self.charge(len)?;
        let mut data = self.bytes_of(data_v, "array data")?.to_vec();
        if order == ByteOrder::Big {
            for item in data.chunks_exact_mut(dtype.itemsize()) {
                item.reverse();
            }
        }
        Ok(NdArray { dtype, shape, fortran_order, data })
    }

    pub(super) fn build(&mut self, target: Val, state: Val) -> Res<()> {
        let Val::Obj(id) = target else {
            return Err(self.invalid(format!("BUILD on a {}", self.kind(target))));
        };
        match self.objs.get(id) {
            Some(Obj::PendingArray) => {
                let array = self.array_state(state)?;
                if let Some(slot) = self.objs.get_mut(id) {
                    *slot = Obj::Array(array);
                }
                Ok(())
            }
            Some(Obj::Dtype { order: None, .. }) => {
                let new_order = self.dtype_state(id, state)?;
                if let Some(Obj::Dtype { order, .. }) = self.objs.get_mut(id) {
                    *order = Some(new_order);
                }
                Ok(())
            }
            Some(Obj::Dtype { .. }) => Err(self.invalid("numpy.dtype state set twice")),
            Some(Obj::Array(_)) => Err(self.invalid("numpy array state set twice")),
            _ => Err(self.invalid(format!(
                "BUILD on a {} (only numpy arrays and dtypes are supported)",
                self.kind(target)
            ))),
        }
    }

    /// ndarray.__setstate__: `(version, shape, dtype, is_fortran, rawdata)`, or the older form
    /// without `version`.
    fn array_state(&mut self, state: Val) -> Res<NdArray> {
        let items = self.tuple_of(state, "numpy array state")?;
        let (shape_v, dtype_v, fortran_v, data_v) = match items {
            [Val::Int(1), s, d, f, r] | [s, d, f, r] => (*s, *d, *f, *r),
            _ => {
                return Err(self.invalid(format!(
                    "numpy array state must be (1, shape, dtype, is_fortran, data), got {} items",
                    items.len()
                )))
            }
        };
        let shape = self.shape_of(shape_v)?;
        let (dtype, order) = self.dtype_of(dtype_v)?;
        let fortran = match fortran_v {
            Val::Bool(b) => b,
            Val::Int(i) => i != 0,
            other => {
                return Err(self.invalid(format!(
                    "numpy array is_fortran must be a bool, got {}",
                    self.kind(other)
                )))
            }
        };
        self.make_array(dtype, order, shape, fortran, data_v)
    }

    /// dtype.__setstate__: `(version, byteorder, subarray, names, fields, elsize, alignment,
    /// flags[, metadata])`. Only plain (non-structured) dtypes are accepted.
    fn dtype_state(&self, id: usize, state: Val) -> Res<ByteOrder> {
        let (dtype, code) = match self.objs.get(id) {
            Some(Obj::Dtype { dtype, code, .. }) => (*dtype, code.as_str()),
            _ => return Err(self.invalid("internal: not a dtype")),
        };
        let items = self.tuple_of(state, "numpy.dtype state")?;
        let [version, order_v, subarray, names, fields, ..] = items else {
            return Err(self.invalid(format!(
                "numpy.dtype('{code}') state has {} items, expected 8 or 9",
                items.len()
            )));
        };
        if !matches!(version, Val::Int(3 | 4)) {
            return Err(self.invalid(format!("numpy.dtype('{code}') state version must be 3 or 4")));
        }
        if ![subarray, names, fields].iter().all(|v| matches!(v, Val::None)) {
            return Err(self.invalid(format!(
                "numpy.dtype('{code}'): structured and subarray dtypes are not supported"
            )));
        }
        let order = match self.str_of(*order_v, "numpy.dtype byte order")? {
            "<" => ByteOrder::Little,
            ">" => ByteOrder::Big,
            "|" => ByteOrder::NotApplicable,
            other => {
                return Err(self.invalid(format!(
                    "numpy.dtype('{code}'): byte order '{}' (expected '<', '>' or '|')",
                    clip(other)
                )))
            }
        };
        if order == ByteOrder::NotApplicable && dtype.itemsize() > 1 {
            return Err(self.invalid(format!(
                "numpy.dtype('{code}'): byte order '|' for a {}-byte type",
                dtype.itemsize()
            )));
        }
        Ok(order)
    }
}
