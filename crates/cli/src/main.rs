fn main() {
    pdt_model::_x();
    println!("ok");
}
