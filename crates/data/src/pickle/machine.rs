//! The pickle stack machine: the [`Machine`] that runs a pickle's opcodes over its object arena.

use std::collections::HashMap;

use super::arena::{over_budget_message, Callable, Obj, Res, Val};
use super::tree::TreeBuilder;
use super::{PickleError, PyValue};
use super::{BUDGET_BASE, BUDGET_PER_INPUT_BYTE, MAX_PROTOCOL};

// The opcode table (`machine/opcodes.rs`) and the callables and BUILD states numpy data uses
// (`machine/calls.rs`), kept apart from the stack machine itself.
mod calls;
mod opcodes;

use opcodes::{op, opcode_name, unsupported_reason};

pub(super) struct Machine<'a> {
    input: &'a [u8],
    pos: usize,
    /// Offset and name of the opcode being executed, for error messages.
    op_at: usize,
    op_name: &'static str,
    stack: Vec<Val>,
    /// Stack lengths at each open MARK. Opcodes may not pop below the innermost mark, as in
    /// Python, where MARK starts a fresh stack.
    marks: Vec<usize>,
    memo: HashMap<u32, Val>,
    objs: Vec<Obj>,
    /// Bytes the reader may still spend on values it creates.
    budget: usize,
}

impl<'a> Machine<'a> {
    pub(super) fn new(input: &'a [u8]) -> Self {
        let budget = input.len().saturating_mul(BUDGET_PER_INPUT_BYTE).saturating_add(BUDGET_BASE);
        Machine {
            input,
            pos: 0,
            op_at: 0,
            op_name: "",
            stack: Vec::new(),
            marks: Vec::new(),
            memo: HashMap::new(),
            objs: Vec::new(),
            budget,
        }
    }

    // --- errors ---------------------------------------------------------------------------------

    fn invalid(&self, message: impl Into<String>) -> PickleError {
        PickleError::Invalid { offset: self.op_at, opcode: self.op_name, message: message.into() }
    }

    fn charge(&mut self, bytes: usize) -> Res<()> {
        match self.budget.checked_sub(bytes) {
            Some(left) => {
                self.budget = left;
                Ok(())
            }
            None => Err(PickleError::Limit {
                offset: self.op_at,
                opcode: self.op_name,
                message: over_budget_message(self.input.len()),
            }),
        }
    }

    // --- reading arguments ----------------------------------------------------------------------

    /// The next `n` bytes; checked against what is left before anything is allocated.
    fn take(&mut self, n: usize, what: impl FnOnce() -> String) -> Res<&'a [u8]> {
        let rest = self.input.get(self.pos..).unwrap_or_default();
        match rest.get(..n) {
            Some(bytes) => {
                self.pos += n;
                Ok(bytes)
            }
            None => Err(PickleError::Truncated {
                offset: self.op_at,
                opcode: self.op_name,
                what: what(),
                available: rest.len(),
            }),
        }
    }

    fn fixed<const N: usize>(&mut self) -> Res<[u8; N]> {
        let bytes = self.take(N, || format!("{N}-byte argument"))?;
        <[u8; N]>::try_from(bytes).map_err(|_| self.invalid("internal: argument size"))
    }

    /// A length-prefixed payload: `len_size` little-endian length bytes, then the data.
    fn payload(&mut self, len_size: usize) -> Res<&'a [u8]> {
        let len_bytes = self.take(len_size, || format!("{len_size}-byte length"))?;
        let mut buf = [0u8; 8];
        for (dst, src) in buf.iter_mut().zip(len_bytes) {
            *dst = *src;
        }
        let n = u64::from_le_bytes(buf);
        // A length that does not fit usize is certainly longer than the input.
        let n_usize = usize::try_from(n).unwrap_or(usize::MAX);
        self.take(n_usize, || format!("length {n}"))
    }

    fn line(&mut self, what: &str) -> Res<&'a str> {
        let rest = self.input.get(self.pos..).unwrap_or_default();
        let Some(end) = rest.iter().position(|&b| b == b'\n') else {
            return Err(PickleError::Truncated {
                offset: self.op_at,
                opcode: self.op_name,
                what: format!("{what} (no newline)"),
                available: rest.len(),
            });
        };
        let bytes = rest.get(..end).unwrap_or_default();
        self.pos += end + 1;
        std::str::from_utf8(bytes).map_err(|_| self.invalid(format!("{what} is not UTF-8")))
    }

    // --- the stack ------------------------------------------------------------------------------

    fn floor(&self) -> usize {
        self.marks.last().copied().unwrap_or(0)
    }

    fn push(&mut self, v: Val) {
        self.stack.push(v);
    }

    fn pop(&mut self) -> Res<Val> {
        if self.stack.len() <= self.floor() {
            return Err(self.invalid("stack underflow"));
        }
        self.stack.pop().ok_or_else(|| self.invalid("stack underflow"))
    }

    fn top(&self) -> Res<Val> {
        if self.stack.len() <= self.floor() {
            return Err(self.invalid("stack underflow"));
        }
        self.stack.last().copied().ok_or_else(|| self.invalid("stack underflow"))
    }

    /// Pops everything above the innermost MARK, and the mark.
    fn pop_mark(&mut self) -> Res<Vec<Val>> {
        let mark = self.marks.pop().ok_or_else(|| self.invalid("no MARK on the stack"))?;
        if mark > self.stack.len() {
            return Err(self.invalid("internal: mark above the stack"));
        }
        Ok(self.stack.split_off(mark))
    }

    fn pop_n(&mut self, n: usize) -> Res<Vec<Val>> {
        let len = self.stack.len();
        if len < self.floor() + n {
            return Err(self.invalid("stack underflow"));
        }
        Ok(self.stack.split_off(len - n))
    }

    fn new_obj(&mut self, obj: Obj) -> Val {
        self.objs.push(obj);
        Val::Obj(self.objs.len() - 1)
    }

    fn obj(&self, v: Val) -> Option<&Obj> {
        match v {
            Val::Obj(id) => self.objs.get(id),
            _ => None,
        }
    }

    /// Python's type name of a stack value, for error messages.
    fn kind(&self, v: Val) -> &'static str {
        match v {
            Val::None => "None",
            Val::Bool(_) => "bool",
            Val::Int(_) => "int",
            Val::Float(_) => "float",
            Val::Obj(_) => match self.obj(v) {
                Some(Obj::Str(_)) => "str",
                Some(Obj::Bytes(_)) => "bytes",
                Some(Obj::List(_)) => "list",
                Some(Obj::Tuple(_)) => "tuple",
                Some(Obj::Dict(_)) => "dict",
                Some(Obj::Callable(_)) => "global",
                Some(Obj::Dtype { .. }) => "numpy.dtype",
                Some(Obj::PendingArray) => "numpy.ndarray (without data)",
                Some(Obj::Array(_)) => "numpy.ndarray",
                None => "?",
            },
        }
    }

    fn str_of(&self, v: Val, what: &str) -> Res<&str> {
        match self.obj(v) {
            Some(Obj::Str(s)) => Ok(s),
            _ => Err(self.invalid(format!("{what} must be a str, got {}", self.kind(v)))),
        }
    }

    fn bytes_of(&self, v: Val, what: &str) -> Res<&[u8]> {
        match self.obj(v) {
            Some(Obj::Bytes(b)) => Ok(b),
            Some(Obj::List(_)) => {
                Err(self.invalid(format!("{what} is a list: object arrays are not supported")))
            }
            _ => Err(self.invalid(format!("{what} must be bytes, got {}", self.kind(v)))),
        }
    }

    fn tuple_of(&self, v: Val, what: &str) -> Res<&[Val]> {
        match self.obj(v) {
            Some(Obj::Tuple(items)) => Ok(items),
            _ => Err(self.invalid(format!("{what} must be a tuple, got {}", self.kind(v)))),
        }
    }

    // --- running --------------------------------------------------------------------------------

    pub(super) fn run(mut self) -> Res<PyValue> {
        loop {
            self.op_at = self.pos;
            let Some(&code) = self.input.get(self.pos) else {
                return Err(PickleError::NoStop { offset: self.pos });
            };
            self.pos += 1;
            let Some(name) = opcode_name(code) else {
                return Err(PickleError::UnknownOpcode { offset: self.op_at, byte: code });
            };
            self.op_name = name;
            if code == op::STOP {
                return self.finish();
            }
            self.step(code)?;
        }
    }

    fn step(&mut self, code: u8) -> Res<()> {
        match code {
            op::PROTO => {
                let [v] = self.fixed::<1>()?;
                if v > MAX_PROTOCOL {
                    return Err(self.invalid(format!("protocol {v} is newer than {MAX_PROTOCOL}")));
                }
            }
            // Frames only tell a streaming reader how much to buffer; the whole input is already
            // in memory, and ignoring them lets a truncated file be reported at the opcode that
            // actually runs out of bytes.
            op::FRAME => {
                self.fixed::<8>()?;
            }
            op::MARK => self.marks.push(self.stack.len()),
            op::POP => {
                // As Python: POP right after a MARK discards the mark.
                if self.stack.len() > self.floor() {
                    self.pop()?;
                } else {
                    self.pop_mark()?;
                }
            }
            op::POP_MARK => {
                self.pop_mark()?;
            }
            op::DUP => {
                let v = self.top()?;
                self.push(v);
            }
            op::NONE => self.push(Val::None),
            op::NEWTRUE => self.push(Val::Bool(true)),
            op::NEWFALSE => self.push(Val::Bool(false)),
            op::BININT => {
                let b = self.fixed::<4>()?;
                self.push(Val::Int(i64::from(i32::from_le_bytes(b))));
            }
            op::BININT1 => {
                let [b] = self.fixed::<1>()?;
                self.push(Val::Int(i64::from(b)));
            }
            op::BININT2 => {
                let b = self.fixed::<2>()?;
                self.push(Val::Int(i64::from(u16::from_le_bytes(b))));
            }
            op::LONG1 => {
                let digits = self.payload(1)?;
                let v = self.long(digits)?;
                self.push(Val::Int(v));
            }
            op::LONG4 => {
                let n = i32::from_le_bytes(self.fixed::<4>()?);
                let n = usize::try_from(n)
                    .map_err(|_| self.invalid(format!("negative LONG4 length {n}")))?;
                let digits = self.take(n, || format!("length {n}"))?;
                let v = self.long(digits)?;
                self.push(Val::Int(v));
            }
            op::BINFLOAT => {
                let b = self.fixed::<8>()?;
                self.push(Val::Float(f64::from_be_bytes(b)));
            }
            op::SHORT_BINUNICODE => self.string(1)?,
            op::BINUNICODE => self.string(4)?,
            op::BINUNICODE8 => self.string(8)?,
            op::SHORT_BINBYTES => self.bytes(1)?,
            op::BINBYTES => self.bytes(4)?,
            op::BINBYTES8 | op::BYTEARRAY8 => self.bytes(8)?,
            op::EMPTY_LIST => {
                let v = self.new_obj(Obj::List(Vec::new()));
                self.push(v);
            }
            op::EMPTY_DICT => {
                let v = self.new_obj(Obj::Dict(Vec::new()));
                self.push(v);
            }
            op::EMPTY_TUPLE => {
                let v = self.new_obj(Obj::Tuple(Vec::new()));
                self.push(v);
            }
            op::LIST => {
                let items = self.pop_mark()?;
                let v = self.new_obj(Obj::List(items));
                self.push(v);
            }
            op::TUPLE => {
                let items = self.pop_mark()?;
                let v = self.new_obj(Obj::Tuple(items));
                self.push(v);
            }
            op::TUPLE1 | op::TUPLE2 | op::TUPLE3 => {
                let items = self.pop_n(usize::from(code - op::TUPLE1 + 1))?;
                let v = self.new_obj(Obj::Tuple(items));
                self.push(v);
            }
            op::DICT => {
                let items = self.pop_mark()?;
                let pairs = self.pairs(items)?;
                let v = self.new_obj(Obj::Dict(pairs));
                self.push(v);
            }
            op::APPEND => {
                let item = self.pop()?;
                self.extend_list(vec![item])?;
            }
            op::APPENDS => {
                let items = self.pop_mark()?;
                self.extend_list(items)?;
            }
            op::SETITEM => {
                let items = self.pop_n(2)?;
                let pairs = self.pairs(items)?;
                self.extend_dict(pairs)?;
            }
            op::SETITEMS => {
                let items = self.pop_mark()?;
                let pairs = self.pairs(items)?;
                self.extend_dict(pairs)?;
            }
            op::BINPUT => {
                let [i] = self.fixed::<1>()?;
                self.put(u32::from(i))?;
            }
            op::LONG_BINPUT => {
                let i = u32::from_le_bytes(self.fixed::<4>()?);
                self.put(i)?;
            }
            op::MEMOIZE => {
                // The memo has at most one entry per opcode, so this fits u32 for any input
                // under 4 GiB; beyond that, refuse rather than wrap.
                let i = u32::try_from(self.memo.len())
                    .map_err(|_| self.invalid("more than 2^32 memo entries"))?;
                self.put(i)?;
            }
            op::BINGET => {
                let [i] = self.fixed::<1>()?;
                self.get(u32::from(i))?;
            }
            op::LONG_BINGET => {
                let i = u32::from_le_bytes(self.fixed::<4>()?);
                self.get(i)?;
            }
            op::GLOBAL => {
                let module = self.line("module name")?;
                let name = self.line("global name")?;
                self.global(module, name)?;
            }
            op::STACK_GLOBAL => {
                let name_v = self.pop()?;
                let module_v = self.pop()?;
                let name = self.str_of(name_v, "STACK_GLOBAL name")?.to_owned();
                let module = self.str_of(module_v, "STACK_GLOBAL module")?.to_owned();
                self.global(&module, &name)?;
            }
            op::REDUCE => {
                let args_v = self.pop()?;
                let callable_v = self.pop()?;
                let callable = match self.obj(callable_v) {
                    Some(Obj::Callable(c)) => *c,
                    _ => {
                        return Err(self.invalid(format!(
                            "REDUCE needs a global to call, got {}",
                            self.kind(callable_v)
                        )))
                    }
                };
                let args = self.tuple_of(args_v, "REDUCE arguments")?.to_vec();
                let result = self.call(callable, &args)?;
                self.push(result);
            }
            op::BUILD => {
                let state = self.pop()?;
                let target = self.top()?;
                self.build(target, state)?;
            }
            other => {
                return Err(PickleError::UnsupportedOpcode {
                    offset: self.op_at,
                    opcode: self.op_name,
                    reason: unsupported_reason(other),
                })
            }
        }
        Ok(())
    }

    /// Python's LONG1/LONG4 payload: little-endian two's complement, any width. Only widths up to
    /// 64 bits are accepted (numpy shapes and the data never need more).
    fn long(&self, digits: &[u8]) -> Res<i64> {
        if digits.len() > 8 {
            return Err(
                self.invalid(format!("integer of {} bytes does not fit in 64 bits", digits.len()))
            );
        }
        let negative = digits.last().is_some_and(|&b| b & 0x80 != 0);
        let mut buf = if negative { [0xff; 8] } else { [0; 8] };
        for (dst, src) in buf.iter_mut().zip(digits) {
            *dst = *src;
        }
        Ok(i64::from_le_bytes(buf))
    }

    fn string(&mut self, len_size: usize) -> Res<()> {
        let raw = self.payload(len_size)?;
        let s =
            std::str::from_utf8(raw).map_err(|e| self.invalid(format!("invalid UTF-8: {e}")))?;
        let v = self.new_obj(Obj::Str(s.to_owned()));
        self.push(v);
        Ok(())
    }

    fn bytes(&mut self, len_size: usize) -> Res<()> {
        let raw = self.payload(len_size)?;
        let v = self.new_obj(Obj::Bytes(raw.to_vec()));
        self.push(v);
        Ok(())
    }

    fn pairs(&self, items: Vec<Val>) -> Res<Vec<(Val, Val)>> {
        if items.len() % 2 == 1 {
            return Err(self.invalid(format!("odd number of items ({}) for a dict", items.len())));
        }
        let mut it = items.into_iter();
        let mut pairs = Vec::with_capacity(it.len() / 2);
        while let (Some(k), Some(v)) = (it.next(), it.next()) {
            pairs.push((k, v));
        }
        Ok(pairs)
    }

    fn extend_list(&mut self, items: Vec<Val>) -> Res<()> {
        let target = self.top()?;
        let kind = self.kind(target);
        match target {
            Val::Obj(id) => match self.objs.get_mut(id) {
                Some(Obj::List(list)) => {
                    list.extend(items);
                    Ok(())
                }
                _ => Err(self.invalid(format!("can only append to a list, not a {kind}"))),
            },
            _ => Err(self.invalid(format!("can only append to a list, not a {kind}"))),
        }
    }

    fn extend_dict(&mut self, pairs: Vec<(Val, Val)>) -> Res<()> {
        let target = self.top()?;
        let kind = self.kind(target);
        match target {
            Val::Obj(id) => match self.objs.get_mut(id) {
                Some(Obj::Dict(dict)) => {
                    dict.extend(pairs);
                    Ok(())
                }
                _ => Err(self.invalid(format!("can only set items on a dict, not a {kind}"))),
            },
            _ => Err(self.invalid(format!("can only set items on a dict, not a {kind}"))),
        }
    }

    fn put(&mut self, index: u32) -> Res<()> {
        let v = self.top()?;
        self.memo.insert(index, v);
        Ok(())
    }

    fn get(&mut self, index: u32) -> Res<()> {
        let v = *self
            .memo
            .get(&index)
            .ok_or_else(|| self.invalid(format!("memo entry {index} does not exist")))?;
        self.push(v);
        Ok(())
    }

    fn global(&mut self, module: &str, name: &str) -> Res<()> {
        match Callable::lookup(module, name) {
            Some(c) => {
                let v = self.new_obj(Obj::Callable(c));
                self.push(v);
                Ok(())
            }
            None => Err(PickleError::GlobalNotAllowed {
                offset: self.op_at,
                opcode: self.op_name,
                module: clip(module),
                name: clip(name),
            }),
        }
    }

    fn finish(mut self) -> Res<PyValue> {
        if !self.marks.is_empty() {
            return Err(self.invalid("STOP with an unclosed MARK"));
        }
        let root = match self.stack.as_slice() {
            [v] => *v,
            other => {
                return Err(self
                    .invalid(format!("STOP with {} values on the stack, expected 1", other.len())))
            }
        };
        let mut tree = TreeBuilder {
            objs: &self.objs,
            budget: &mut self.budget,
            input_len: self.input.len(),
            op_at: self.op_at,
        };
        tree.value(root, 0)
    }
}

/// Keeps strings from the input short in error messages.
fn clip(s: &str) -> String {
    const MAX: usize = 200;
    match s.char_indices().nth(MAX) {
        Some((cut, _)) => format!("{}...", s.get(..cut).unwrap_or_default()),
        None => s.to_owned(),
    }
}
