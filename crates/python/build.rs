// The extension finds the libtorch and MuJoCo libraries bundled beside it in the wheel
// (promptdt/_libs, copied there by scripts/install_python.sh) through an $ORIGIN rpath. The
// workspace's own rpaths (.cargo/config.toml) point at third_party/ relative to target/, which
// means nothing once the module is installed in a virtual environment.
fn main() {
    println!("cargo:rustc-link-arg-cdylib=-Wl,-rpath,$ORIGIN/_libs");
}
