#!/bin/bash
cd /work/main
E=target/symsol/experts
exec ./target/release/alignist-train fit --fresh \
  --experts $E/tet --experts $E/cube --experts $E/icosa --experts $E/cone --experts $E/cyl \
  --method alignist --image-size 32 --steps 16000 --batch 16 --k 256 --lr 1e-3 \
  --eval-level 3 --eval-images 50 --checkpoint-every 500 --seed 0 --profile --resume \
  --out target/symsol/models/alignist-fresh
