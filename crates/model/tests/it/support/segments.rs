//! Random left-padded segments for the model's tests.

use pdt_model::Segments;
use tch::{Device, Kind, Tensor};

/// `b` segments of `t` steps, left-padded to random lengths (at least 1 real step).
pub fn segments(b: i64, t: i64, ds: i64, da: i64) -> Segments {
    let tlen = Tensor::randint_low(1, t + 1, [b], (Kind::Int64, Device::Cpu));
    let pos = Tensor::arange(t, (Kind::Int64, Device::Cpu));
    let mask = pos.unsqueeze(0).ge_tensor(&(t - tlen).unsqueeze(1)); // [b, t]
    let start = Tensor::randint_low(0, 200 - t, [b, 1], (Kind::Int64, Device::Cpu));
    let timesteps = (start + pos.unsqueeze(0))
        .where_self(&mask, &Tensor::zeros([1], (Kind::Int64, Device::Cpu)));
    let m = mask.to_kind(Kind::Float);
    Segments {
        states: Tensor::randn([b, t, ds], (Kind::Float, Device::Cpu)) * m.unsqueeze(-1),
        actions: (Tensor::rand([b, t, da], (Kind::Float, Device::Cpu)) * 2.0 - 1.0)
            * m.unsqueeze(-1),
        returns_to_go: Tensor::rand([b, t, 1], (Kind::Float, Device::Cpu)),
        timesteps,
        mask: m,
    }
}
