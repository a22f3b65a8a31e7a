//! [`TreeBuilder`]: turns the machine's arena of objects into an owned [`PyValue`] tree.

use std::collections::HashMap;

use super::arena::{over_budget_message, Obj, Res, Val};
use super::{PickleError, PyValue, MAX_DEPTH};

/// Turns the arena of objects into an owned tree, within the depth and memory budget.
pub(super) struct TreeBuilder<'m> {
    pub(super) objs: &'m [Obj],
    pub(super) budget: &'m mut usize,
    pub(super) input_len: usize,
    pub(super) op_at: usize,
}

impl TreeBuilder<'_> {
    fn error(&self, message: String) -> PickleError {
        PickleError::Invalid { offset: self.op_at, opcode: "STOP", message }
    }

    fn charge(&mut self, bytes: usize) -> Res<()> {
        match self.budget.checked_sub(bytes) {
            Some(left) => {
                *self.budget = left;
                Ok(())
            }
            None => Err(PickleError::Limit {
                offset: self.op_at,
                opcode: "STOP",
                message: over_budget_message(self.input_len),
            }),
        }
    }

    pub(super) fn value(&mut self, v: Val, depth: usize) -> Res<PyValue> {
        self.charge(std::mem::size_of::<PyValue>())?;
        let id = match v {
            Val::None => return Ok(PyValue::None),
            Val::Bool(b) => return Ok(PyValue::Bool(b)),
            Val::Int(i) => return Ok(PyValue::Int(i)),
            Val::Float(f) => return Ok(PyValue::Float(f)),
            Val::Obj(id) => id,
        };
        let objs = self.objs;
        let Some(obj) = objs.get(id) else {
            return Err(self.error("internal: dangling object".into()));
        };
        let is_container = matches!(obj, Obj::List(_) | Obj::Tuple(_) | Obj::Dict(_));
        if is_container && depth >= MAX_DEPTH {
            return Err(PickleError::Limit {
                offset: self.op_at,
                opcode: "STOP",
                message: format!(
                    "containers nested more than {MAX_DEPTH} deep (or a container that contains \
                     itself)"
                ),
            });
        }
        Ok(match obj {
            Obj::Str(s) => {
                self.charge(s.len())?;
                PyValue::Str(s.clone())
            }
            Obj::Bytes(b) => {
                self.charge(b.len())?;
                PyValue::Bytes(b.clone())
            }
            Obj::List(items) => PyValue::List(self.values(items, depth)?),
            Obj::Tuple(items) => PyValue::Tuple(self.values(items, depth)?),
            Obj::Dict(pairs) => self.dict(pairs, depth)?,
            Obj::Array(a) => {
                self.charge(a.data.len())?;
                PyValue::NdArray(a.clone())
            }
            Obj::Dtype { dtype, .. } => PyValue::DType(*dtype),
            Obj::Callable(c) => {
                return Err(self.error(format!(
                    "global {} appears as a value; it is only accepted as something to call",
                    c.name()
                )))
            }
            Obj::PendingArray => {
                return Err(self.error(
                    "a numpy array made by _reconstruct never received its data (no BUILD)".into(),
                ))
            }
        })
    }

    fn values(&mut self, items: &[Val], depth: usize) -> Res<Vec<PyValue>> {
        items.iter().map(|&item| self.value(item, depth + 1)).collect()
    }

    /// Builds a dict as Python would: a repeated key keeps its first position and takes the
    /// last value.
    fn dict(&mut self, pairs: &[(Val, Val)], depth: usize) -> Res<PyValue> {
        let mut out: Vec<(PyValue, PyValue)> = Vec::new();
        let mut index: HashMap<String, usize> = HashMap::new();
        for &(k, v) in pairs {
            let key = self.value(k, depth + 1)?;
            let value = self.value(v, depth + 1)?;
            let Some(hash_key) = hash_key(&key) else {
                return Err(self.error(format!("unhashable dict key of type {}", key.type_name())));
            };
            self.charge(hash_key.len())?;
            match index.get(&hash_key).and_then(|&i| out.get_mut(i)) {
                Some(slot) => slot.1 = value,
                None => {
                    index.insert(hash_key, out.len());
                    out.push((key, value));
                }
            }
        }
        Ok(PyValue::Dict(out))
    }
}

/// A string equal for keys that Python's dict treats as the same key (`1 == 1.0 == True`), or
/// `None` for unhashable values.
fn hash_key(v: &PyValue) -> Option<String> {
    Some(match v {
        PyValue::None => "n".into(),
        PyValue::Bool(b) => format!("i{}", i64::from(*b)),
        PyValue::Int(i) => format!("i{i}"),
        PyValue::Float(f) => {
            if f.fract() == 0.0 && f.abs() < 9.2e18 {
                format!("i{}", *f as i64)
            } else {
                format!("f{}", f.to_bits())
            }
        }
        PyValue::Str(s) => format!("s{s}"),
        PyValue::Bytes(b) => format!("b{b:?}"),
        PyValue::DType(d) => format!("d{}", d.name()),
        PyValue::Tuple(items) => {
            let parts: Option<Vec<String>> = items.iter().map(hash_key).collect();
            format!("t({})", parts?.join(","))
        }
        PyValue::List(_) | PyValue::Dict(_) | PyValue::NdArray(_) => return None,
    })
}
