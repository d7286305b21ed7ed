fn main() {
    println!("quantacolor");
}
