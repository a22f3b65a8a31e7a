//! Reach's task lists: numpy-compatible ML1 task vectors (numpy's legacy `RandomState` and
//! reach's rejection loop), as Meta-World draws them.

use super::{NUM_TASKS, RESET_HIGH, RESET_LOW};

/// numpy's legacy `RandomState`: MT19937 seeded with `init_genrand(seed)` (what
/// `np.random.seed(int)` does), doubles from two 32-bit draws (`random_sample`).
#[derive(Clone)]
pub struct NumpyRandomState {
    mt: [u32; 624],
    index: usize,
}

impl NumpyRandomState {
    pub fn new(seed: u32) -> Self {
        let mut mt = [0u32; 624];
        mt[0] = seed;
        for i in 1..624 {
            let prev = mt[i - 1];
            // Knuth's multiplier of the reference init_genrand; `i` < 624 fits in u32.
            mt[i] = 1_812_433_253u32.wrapping_mul(prev ^ (prev >> 30)).wrapping_add(i as u32);
        }
        Self { mt, index: 624 }
    }

    pub fn next_u32(&mut self) -> u32 {
        if self.index >= 624 {
            self.twist();
        }
        let mut y = self.mt[self.index];
        self.index += 1;
        y ^= y >> 11;
        y ^= (y << 7) & 0x9d2c_5680;
        y ^= (y << 15) & 0xefc6_0000;
        y ^ (y >> 18)
    }

    fn twist(&mut self) {
        const UPPER: u32 = 0x8000_0000;
        const LOWER: u32 = 0x7fff_ffff;
        for i in 0..624 {
            let y = (self.mt[i] & UPPER) | (self.mt[(i + 1) % 624] & LOWER);
            let mag = if y & 1 == 1 { 0x9908_b0df } else { 0 };
            self.mt[i] = self.mt[(i + 397) % 624] ^ (y >> 1) ^ mag;
        }
        self.index = 0;
    }

    /// numpy's `random_sample`: a 53-bit double in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        let a = self.next_u32() >> 5;
        let b = self.next_u32() >> 6;
        (f64::from(a) * 67_108_864.0 + f64::from(b)) / 9_007_199_254_740_992.0
    }

    /// `np.random.uniform(low, high)` element-wise, as numpy computes it: `low + (high - low) * u`.
    pub fn uniform<const N: usize>(&mut self, low: &[f64; N], high: &[f64; N]) -> [f64; N] {
        let mut out = [0.0; N];
        for i in 0..N {
            let range = high[i] - low[i];
            out[i] = low[i] + range * self.next_f64();
        }
        out
    }
}

/// Which Meta-World version's ML1 list to produce. Both draw task vectors from the global numpy
/// RNG seeded with the ML1 seed, one vector per `reset`, but the versions differ in how many
/// rejection loops one `reset` runs (spec §2.5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TaskList {
    /// `ML1('reach-v2', seed)` of the 2021 code Prompt-DT vendored: one loop per reset.
    Legacy,
    /// `ML1('reach-v3', seed)` of metaworld 3.x: `reset_model` runs twice per reset; the second
    /// vector is kept.
    V3,
}

/// One draw of reach's `reset_model`: uniform vectors until object and goal are at least 0.15
/// apart in the plane.
fn draw_task(rng: &mut NumpyRandomState) -> [f64; 6] {
    loop {
        let v = rng.uniform(&RESET_LOW, &RESET_HIGH);
        let (dx, dy) = (v[0] - v[3], v[1] - v[4]);
        // np.linalg.norm summed left to right (OpenBLAS's Haswell/Zen kernels; its AVX-512 kernel
        // fuses the multiply-add, which could only matter within an ulp of 0.15).
        if (dx * dx + dy * dy).sqrt() >= 0.15 {
            return v;
        }
    }
}

/// The 50 task vectors (object xyz | goal xyz) of `ML1('reach-v2' or 'reach-v3', seed)`'s train
/// list; the test list is the same with `seed + 1`.
pub fn ml1_tasks(seed: u32, list: TaskList) -> Vec<[f64; 6]> {
    let mut rng = NumpyRandomState::new(seed);
    let draws = match list {
        TaskList::Legacy => 1,
        TaskList::V3 => 2,
    };
    (0..NUM_TASKS)
        .map(|_| {
            let mut v = draw_task(&mut rng);
            for _ in 1..draws {
                v = draw_task(&mut rng);
            }
            v
        })
        .collect()
}
