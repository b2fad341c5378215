pub mod recon;

pub mod cli {
    pub fn main() {}
}
