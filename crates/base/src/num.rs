//! Numbers as messages print them.

/// A number as messages print it: plainly when it is of ordinary size, in exponent form when it
/// is huge or tiny (`{}` prints 1e300 with all its 301 digits).
pub fn compact<T: Into<f64> + Copy + std::fmt::Display + std::fmt::LowerExp>(x: T) -> String {
    let v: f64 = x.into();
    if v == 0.0 || !v.is_finite() || (1e-4..1e6).contains(&v.abs()) {
        format!("{x}")
    } else {
        // In the value's own type, so an f32 prints its shortest form (1e30, not
        // 1.0000000150474662e30).
        format!("{x:e}")
    }
}

#[cfg(test)]
mod tests {
    use super::compact;

    #[test]
    fn huge_and_tiny_numbers_print_in_exponent_form() {
        assert_eq!(compact(1e300), "1e300");
        assert_eq!(compact(1e30f32), "1e30");
        assert_eq!(compact(-2.5e-9), "-2.5e-9");
        assert_eq!(compact(0.3), "0.3");
        assert_eq!(compact(0.0), "0");
        assert_eq!(compact(f64::NAN), "NaN");
    }
}
