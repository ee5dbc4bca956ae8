#!/usr/bin/env bash
# Sourced by the device scripts that time commands: Python byte-code compiled once, as `pip install`
# leaves an installation, so that a command's wall time is the product's and not the device image's.
#
#   source benchmarks/gpu/bytecode.sh        # after the build; PY (default python3) is the interpreter
#
# The GPU machine's image sets PYTHONDONTWRITEBYTECODE=1 and ships its site-packages without
# __pycache__: every process there compiled torch, sympy, transformers and diffusers from source, ~10 s
# of each `tiger edit` (H100: 107.9 s with it, 94.9 s without; docs/BENCHMARKS.md, "`tiger edit` end
# to end"). The byte-code goes to a prefix (PYTHONPYCACHEPREFIX) because the image's folders may be
# read-only; a machine whose interpreter writes byte-code itself is left as it is.
_bytecode_py="${PY:-python3}"
if [ -n "${PYTHONDONTWRITEBYTECODE:-}" ] || [ -n "${PYTHONPYCACHEPREFIX:-}" ]; then
  export PYTHONPYCACHEPREFIX="${PYTHONPYCACHEPREFIX:-/tmp/tiger-pycache}"
  _bytecode_dirs=$("$_bytecode_py" -c 'import site, sys, os; print(" ".join(p for p in [*site.getsitepackages(), *sys.path[1:]] if os.path.isdir(p) and "lib-dynload" not in p))')
  _bytecode_t0=$(date +%s)
  "$_bytecode_py" -m compileall -q -j 0 $_bytecode_dirs tiger benchmarks > /dev/null 2>&1
  echo "byte-code compiled into $PYTHONPYCACHEPREFIX in $(( $(date +%s) - _bytecode_t0 )) s"
fi
unset _bytecode_py _bytecode_dirs _bytecode_t0
