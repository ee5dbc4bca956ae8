#!/usr/bin/env bash
# Download (here, where PyPI is reachable) the wheels the notebook tests need on the device
# (CPython 3.12, x86-64): nbformat, nbclient, ipykernel and everything they require, minus what
# the device image already has. Use: bash benchmarks/gpu/test_wheels.sh DIR, then carry DIR and
# run check.sh with TEST_WHEELS=DIR (and TEST_DATA=the shared data folder for the fox tests).
set -euo pipefail
DIR="${1:?usage: test_wheels.sh DIR}"
python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d "$DIR" nbformat nbclient ipykernel
rm -f "$DIR"/typing_extensions-* "$DIR"/packaging-*  # the device's own versions stay in charge
ls "$DIR"
