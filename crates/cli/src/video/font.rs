//! A tiny built-in 3 x 5 bitmap font for the text drawn on rendered frames (a video's return and
//! step), so no font file or text library is needed.

use pdt_envs::render::Frame;

/// Glyph rows, top first; each row's 3 low bits are its pixels, left to right.
fn glyph(c: char) -> [u8; 5] {
    match c {
        '0' => [0b111, 0b101, 0b101, 0b101, 0b111],
        '1' => [0b010, 0b110, 0b010, 0b010, 0b111],
        '2' => [0b111, 0b001, 0b111, 0b100, 0b111],
        '3' => [0b111, 0b001, 0b111, 0b001, 0b111],
        '4' => [0b101, 0b101, 0b111, 0b001, 0b001],
        '5' => [0b111, 0b100, 0b111, 0b001, 0b111],
        '6' => [0b111, 0b100, 0b111, 0b101, 0b111],
        '7' => [0b111, 0b001, 0b010, 0b010, 0b010],
        '8' => [0b111, 0b101, 0b111, 0b101, 0b111],
        '9' => [0b111, 0b101, 0b111, 0b001, 0b111],
        '-' => [0b000, 0b000, 0b111, 0b000, 0b000],
        '+' => [0b000, 0b010, 0b111, 0b010, 0b000],
        '.' => [0b000, 0b000, 0b000, 0b000, 0b010],
        '=' => [0b000, 0b111, 0b000, 0b111, 0b000],
        'R' => [0b110, 0b101, 0b110, 0b101, 0b101],
        't' => [0b010, 0b111, 0b010, 0b010, 0b011],
        'e' => [0b000, 0b111, 0b111, 0b100, 0b111],
        // Anything else (a space included) is blank.
        _ => [0; 5],
    }
}

/// Width in pixels of `text` drawn at `scale` (4 columns a character, the last without a gap).
pub fn text_width(text: &str, scale: usize) -> usize {
    (text.chars().count() * 4).saturating_sub(1) * scale
}

/// Draws `text` with its top-left corner at (x, y), each font pixel a `scale` x `scale` square,
/// on a dark box one font pixel wider all around (readable on any scene).
pub fn draw_text(f: &mut Frame, x: usize, y: usize, scale: usize, text: &str, color: [u8; 3]) {
    let (w, h) = (text_width(text, scale) + 2 * scale, 7 * scale);
    for py in y..y + h {
        for px in x..x + w {
            f.put(px as i64, py as i64, [20, 20, 20]);
        }
    }
    for (i, c) in text.chars().enumerate() {
        let left = x + scale + i * 4 * scale;
        for (row, bits) in glyph(c).iter().enumerate() {
            for col in 0..3 {
                if bits & (0b100 >> col) == 0 {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        let px = left + col * scale + dx;
                        let py = y + (row + 1) * scale + dy;
                        f.put(px as i64, py as i64, color);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pdt_envs::render::FrameSize;

    #[test]
    fn digits_differ_and_text_lands_in_its_box() {
        let glyphs: Vec<[u8; 5]> = "0123456789".chars().map(glyph).collect();
        for (i, a) in glyphs.iter().enumerate() {
            for b in &glyphs[i + 1..] {
                assert_ne!(a, b);
            }
        }
        let size = FrameSize::new(40, 20).unwrap_or_else(|e| panic!("{e}"));
        let mut f = Frame::filled(size, [255, 255, 255]);
        draw_text(&mut f, 2, 3, 1, "R=-1.5", [255, 255, 0]);
        let px = |x: usize, y: usize| &f.rgb[(y * 40 + x) * 3..(y * 40 + x) * 3 + 3];
        // The box: 6 characters * 4 - 1 + 2 = 25 wide, 7 high; outside it untouched.
        assert_eq!(px(2, 3), [20, 20, 20]);
        assert_eq!(px(27, 3), [255, 255, 255]);
        assert_eq!(px(2, 10), [255, 255, 255]);
        // 'R''s top-left pixel.
        assert_eq!(px(3, 4), [255, 255, 0]);
    }
}
