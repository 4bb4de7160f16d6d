#!/usr/bin/env bash
# Remakes every bundled bag from its scene file with the project's simulator:
#   bags/make.sh            (from the repository root)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo build --quiet --release
for scene in bags/*.toml; do
    ./target/release/translucent_tof simulate "$scene" -o "${scene%.toml}.mcap"
done
