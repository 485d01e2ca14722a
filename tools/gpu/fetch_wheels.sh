#!/usr/bin/env bash
# Download the wheels of tools/gpu/wheels.txt into .whl/ (CPython 3.12, manylinux x86-64) for the GPU machine,
# which reaches no registry. Run here, in the repo root, where pip reaches the registry:
#   bash tools/gpu/fetch_wheels.sh
# .whl/ is ignored through .git/info/exclude and travels with the run tool's carry [".whl"]; the working tree
# plus carried paths must stay under 64 MiB. tools/gpu/session.sh installs them on the device (--no-deps).
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
PIP="${PIP:-python3 -m pip}"
exclude="$(git rev-parse --git-dir)/info/exclude"
mkdir -p "$(dirname "$exclude")" .whl
grep -qxF '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >>"$exclude"
mapfile -t wanted < <(grep -vE '^\s*(#|$)' tools/gpu/wheels.txt)
plat=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_24_x86_64 manylinux_2_17_x86_64 \
         manylinux2014_x86_64 manylinux1_x86_64; do plat+=(--platform "$p"); done
quiet() { grep -v "^WARNING: Location" || true; }  # this machine's pip config names local indexes that may be absent
for spec in "${wanted[@]}"; do
  if ! $PIP download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${plat[@]}" \
       -d .whl "$spec" 2> >(quiet >&2); then
    # no wheel on the registry (antlr4-python3-runtime 4.9.3 is an sdist): build it, pure Python only
    echo "no wheel for $spec: building one from the sdist" >&2
    $PIP wheel -q --no-deps -w .whl "$spec" 2> >(quiet >&2)
  fi
done
# keep exactly one wheel per listed NAME==VERSION (two versions of one package stop the install on the device)
python3 - <<'PY'
import pathlib
import re

def norm(s):
    return re.sub(r"[-_.]+", "_", s).lower()

want = {}
for line in open("tools/gpu/wheels.txt"):
    line = line.strip()
    if line and not line.startswith("#"):
        name, ver = line.split("==")
        want[norm(name)] = ver
seen = set()
for w in sorted(pathlib.Path(".whl").glob("*.whl")):
    name, ver = w.name.split("-")[:2]
    if want.get(norm(name)) != ver:
        print("removing", w.name)
        w.unlink()
    else:
        seen.add(norm(name))
missing = sorted(set(want) - seen)
if missing:
    raise SystemExit(f"missing wheels: {missing}")
bad = [w.name for w in pathlib.Path(".whl").glob("*.whl") if not re.search(r"(cp312|py3|py2\.py3)-[^-]+-(any|manylinux)", w.name)]
if bad:
    raise SystemExit(f"wheels not for CPython 3.12 / manylinux x86-64: {bad}")
PY
echo "$(ls .whl/*.whl | wc -l) wheels in .whl/, $(du -sm .whl | cut -f1) MiB"
