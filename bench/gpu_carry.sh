#!/usr/bin/env bash
# Prepares what bench/gpu_device.sh needs on the lent GPU machine (issue 17), which reaches no package index and
# sees the repository but not ../shared: the wheels its image lacks (CPython 3.12, manylinux x86-64; versions as
# in this .venv, imageio-ffmpeg at 0.5.1 whose wheel is 27 MB rather than 68) and mic's train and test views (the listed ones).
# Everything lands in .gpu_carry/ (gitignored), which must stay under the device's 64 MiB with the repository.
#
#   bash bench/gpu_carry.sh        # here, once (needs PyPI)
#   then, with the device tool:    run(command="bash bench/gpu_device.sh", carry=[".gpu_carry"], timeout_s=600)
set -euo pipefail
cd "$(dirname "$0")/.."
CARRY=.gpu_carry
DATA=${VOXE_DATA_ROOT:-../shared/data}
PACKAGES="diffusers fastapi starlette pydantic pydantic_core pydantic-settings python-dotenv annotated-types
  typing-inspection python-multipart SQLAlchemy alembic Mako celery kombu billiard vine amqp tzlocal
  click-didyoumean click-plugins click-repl prompt_toolkit wcwidth PyMaxflow trimesh sniffio opentelemetry-api"
pinned=()
for name in $PACKAGES; do
    version=$(.venv/bin/python -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$name")
    pinned+=("$name==$version")
done
pinned+=("imageio-ffmpeg==0.5.1")
rm -rf "$CARRY" && mkdir -p "$CARRY/whl" "$CARRY/shared/data/nerf_synthetic_mic"
tags=()
for tag in manylinux2010 manylinux2014 manylinux_2_17 manylinux_2_24 manylinux_2_27 manylinux_2_28 manylinux_2_31 \
           manylinux_2_34; do tags+=(--platform "${tag}_x86_64"); done
.venv/bin/python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${tags[@]}" -d "$CARRY/whl" "${pinned[@]}"
mic="$DATA/nerf_synthetic_mic"
for split in train test; do  # the views each split's transforms list, not the depth and normal maps beside them
    cp "$mic/transforms_$split.json" "$CARRY/shared/data/nerf_synthetic_mic/"
    mkdir -p "$CARRY/shared/data/nerf_synthetic_mic/$split"
    .venv/bin/python -c "import json, sys; print('\n'.join(f['file_path'] + '.png' for f in json.load(open(sys.argv[1]))['frames']))" \
        "$mic/transforms_$split.json" | while read -r view; do cp "$mic/$view" "$CARRY/shared/data/nerf_synthetic_mic/$view"; done
done
tree_mib=$(git ls-files -z | du -cb --files0-from=- | tail -1 | cut -f1)
carry_mib=$(du -sb "$CARRY" | cut -f1)
total=$(( (tree_mib + carry_mib) / 1048576 ))
echo "carry: $(ls "$CARRY/whl" | wc -l) wheels + mic train/test; repository + carry = ${total} MiB (device limit 64)"
[ "$total" -lt 64 ] || { echo "over the device's 64 MiB: carry less" >&2; exit 1; }
