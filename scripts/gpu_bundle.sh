#!/usr/bin/env bash
# Builds gpu_bundle/: everything `dust-rl bench gpu` needs on a GPU machine without network access whose
# Python already has torch, numpy, transformers, safetensors and the like (run the check there with
# scripts/gpu_check.sh). Needs network here and the project's .venv (bash scripts/setup.sh).
#   wheels/         dust-rl itself, and mujoco, torchrl, tensordict, gymnasium, mink, tyro, SB3 and what they
#                   need, for that machine's Python (PY, default 3.12), x86-64 Linux
#   debs/           the EGL/GL loader libraries, unpacked there only if it has no libEGL
#   franka.tar.xz   the Panda model of MuJoCo Menagerie (3 MB instead of 35 MB of meshes)
#   text_encoder/   a small randomly initialised BERT with MiniLM's tokenizer: the check times the loop,
#                   not the policy's skill, so MiniLM's 87 MB of weights stay behind
# About 45 MB in all. Usage: bash scripts/gpu_bundle.sh [PY]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${1:-3.12}
BUNDLE=gpu_bundle
rm -rf $BUNDLE && mkdir -p $BUNDLE/wheels $BUNDLE/debs

# Pinned packages take their exact versions from constraints.txt (declared once); the rest are what those need.
pinned=$(grep -E '^(mujoco|torchrl|tensordict|gymnasium|mink|tyro|stable-baselines3)==' constraints.txt)
unpinned="farama-notifications quadprog daqp qpsolvers mujoco-menagerie pyopengl glfw websockets importlib_metadata
lazy-importer orjson pyvers hoptorch docstring-parser typeguard"
for requirement in $pinned $unpinned; do
  python3 -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version "$PY" \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
    -d $BUNDLE/wheels "$requirement"
done
.venv/bin/python -m pip wheel -q --disable-pip-version-check --no-deps --no-build-isolation -w $BUNDLE/wheels .
rm -rf build  # setuptools' staging folder

mkdir -p /tmp/dust_rl_apt/partial
apt_opts='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/dust_rl_apt'
apt-get $apt_opts update -qq
(cd $BUNDLE/debs && apt-get $apt_opts download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 2>/dev/null)

menagerie=$(.venv/bin/python -c "from dust_rl.envs.assets import robot_xml; print(robot_xml('franka_emika_panda').parent.parent)")
tar -cJf $BUNDLE/franka.tar.xz -C "$menagerie" franka_emika_panda/panda.xml franka_emika_panda/assets \
  franka_emika_panda/LICENSE

.venv/bin/python - $BUNDLE/text_encoder <<'EOF'
import sys

import torch
from transformers import AutoTokenizer, BertConfig, BertModel

from dust_rl.agents.encoders.text_encoder import minilm_path

tokenizer = AutoTokenizer.from_pretrained(minilm_path(), local_files_only=True)
torch.manual_seed(0)
model = BertModel(BertConfig(vocab_size=tokenizer.vocab_size, hidden_size=32, num_hidden_layers=1,
                             num_attention_heads=2, intermediate_size=64))
model.save_pretrained(sys.argv[1])
tokenizer.save_pretrained(sys.argv[1])
EOF
du -sh $BUNDLE
