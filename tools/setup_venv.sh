#!/usr/bin/env bash
# Set up .venv for galvoscan without a system ROS install.
#
#   tools/setup_venv.sh deps   create .venv, install pinned wheels (requirements.txt + constraints.txt)
#   tools/setup_venv.sh msgs   build msgs_vendor/tf2_msgs and msgs/ (galvoscan_msgs) with cmake into the venv prefix
#   tools/setup_venv.sh src    install the src/ packages into the venv (editable)
#   tools/setup_venv.sh apt    install the Debian packages the tests need (tools/apt-packages.txt)
#   tools/setup_venv.sh web    vendor three.js (npm, src/galvoscan_view/web) into the view page's static/vendor
#
# The Makefile calls each step only when its inputs changed. Nothing outside the
# repository is modified.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=$ROOT/.venv
PY=$VENV/bin/python
PYTHON=${PYTHON:-python3}

step_deps() {
  if [ ! -x "$PY" ]; then
    echo "[setup] creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv "$VENV"
  fi
  echo "[setup] installing pinned packages (first run: a few minutes, mostly downloads)"
  "$PY" -m pip install --disable-pip-version-check -q -r requirements.txt -c constraints.txt
  # open3d links libusb-1.0.so.0; the ROS wheels' start-up hook puts .venv/lib on
  # LD_LIBRARY_PATH, so a link there is found without touching the system.
  local libusb
  libusb=$("$PY" -c 'import libusb_package, os; print(os.path.join(os.path.dirname(libusb_package.__file__), "libusb-1.0.so"))')
  ln -sf "$libusb" "$VENV/lib/libusb-1.0.so.0"
  # Aravis (galvo_driver.genicam_camera) is reached through PyGObject: link only Debian's
  # python3-gi package `gi` (tools/apt-packages.txt, built for this Python 3.11) into the
  # venv; the link dangles harmlessly until the apt step has installed it.
  ln -sfn /usr/lib/python3/dist-packages/gi \
    "$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/gi"
  "$PY" -c 'import rclpy, numpy, scipy, cv2, open3d, rosbags, mcap, serial' 
}

step_msgs() {
  # Known defect of the wheels: their exported CMake files name the wheel builder's
  # Python include and numpy include paths. Rewrite them to this interpreter's, inside
  # the venv only.
  local pyinc npinc
  pyinc=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  npinc=$("$PY" -c 'import numpy; print(numpy.get_include())')
  { grep -rlE '/opt/python/cp311-cp311/(include/python3.11|lib/python3.11/site-packages/numpy/_core/include)' \
      "$VENV/share" --include='*.cmake' 2>/dev/null || true; } | while read -r f; do
    sed -i -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$npinc#g" \
           -e "s#/opt/python/cp311-cp311/include/python3.11#$pyinc#g" "$f"
  done
  # tf2_msgs (msgs_vendor/, upstream's interface files; no PyPI wheel has it), then ours.
  local src name build
  for src in msgs_vendor/tf2_msgs msgs; do
    name=$(sed -n 's#.*<name>\(.*\)</name>.*#\1#p' "$src/package.xml")
    build=$ROOT/build/$src
    rm -rf "$build"
    mkdir -p "$build"
    echo "[setup] building $name"
    (
      cd "$build"
      export AMENT_PREFIX_PATH=$VENV CMAKE_PREFIX_PATH=$VENV
      # The generators run with the venv's python and must find its site-packages.
      export PATH=$VENV/bin:$PATH
      cmake "$ROOT/$src" -DCMAKE_INSTALL_PREFIX="$VENV" -DPython3_EXECUTABLE="$PY" \
            -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >cmake.log 2>&1 \
        || { tail -40 cmake.log; echo "[setup] cmake configure of $src failed (log: $build/cmake.log)"; exit 1; }
      make -j"$(nproc)" install >make.log 2>&1 \
        || { tail -40 make.log; echo "[setup] build of $src failed (log: $build/make.log)"; exit 1; }
    )
  done
  (cd /tmp && env -u AMENT_PREFIX_PATH "$PY" -c 'import galvoscan_msgs.msg, galvoscan_msgs.srv, tf2_msgs.msg, tf2_msgs.srv, tf2_msgs.action')
  echo "[setup] galvoscan_msgs and tf2_msgs installed into .venv"
}

step_src() {
  echo "[setup] installing src packages (editable)"
  local args=()
  for p in galvoscan_common galvoscan_sim galvoscan_bag galvo_driver stripe_extractor reconstructor calibration_tools galvoscan_view galvoscan; do
    args+=(-e "src/$p")
  done
  "$PY" -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation --use-pep517 "${args[@]}"
}

# How long apt-get waits for another package manager (an unattended upgrade, another
# apt-get) to release the dpkg lock before it gives up [s]; APT_LOCK_TIMEOUT overrides it.
APT_LOCK_TIMEOUT=${APT_LOCK_TIMEOUT:-600}

# Run apt-get with the lock timeout, its output in a log; on failure say what to do.
apt_get() {
  local log
  log=$(mktemp)
  if "${sudo[@]}" apt-get -o "DPkg::Lock::Timeout=$APT_LOCK_TIMEOUT" "$@" >"$log" 2>&1; then
    rm -f "$log"; return 0
  fi
  if grep -qiE 'could not get lock|unable to acquire the dpkg|lock-frontend|is held by process' "$log"; then
    echo "[setup] apt-get $1: the dpkg lock is still held by another process after waiting" \
         "${APT_LOCK_TIMEOUT} s:"
    grep -iE 'lock' "$log" | head -3 | sed 's/^/[setup]   /'
    echo "[setup] another package manager is running (an unattended upgrade, another apt-get)." \
         "Wait until it has finished (ps -C apt,apt-get,dpkg,unattended-upgr), then run the" \
         "same make command again; or wait longer: APT_LOCK_TIMEOUT=1800 make test"
  else
    tail -20 "$log" | sed 's/^/[setup]   /'
    echo "[setup] apt-get $* failed (above); install the packages of tools/apt-packages.txt" \
         "yourself, then run the same make command again"
  fi
  rm -f "$log"
  exit 1
}

step_apt() {
  local wanted=() missing=()
  mapfile -t wanted < <(grep -vE '^\s*(#|$)' tools/apt-packages.txt)
  for p in "${wanted[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  echo "[setup] installing Debian packages: ${missing[*]} (waiting up to ${APT_LOCK_TIMEOUT} s" \
       "for another package manager to finish)"
  sudo=()
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || { echo "[setup] need root (or sudo) to install: ${missing[*]}"; exit 1; }
    sudo=(sudo)
  fi
  export DEBIAN_FRONTEND=noninteractive
  apt_get update -qq
  apt_get install -y -qq --no-install-recommends "${missing[@]}"
}

step_web() {
  # three.js for the browser page of galvoscan view, at the exact version of
  # src/galvoscan_view/web/package-lock.json, copied into the package's static/vendor:
  # the page loads nothing from the internet at run time.
  local web=src/galvoscan_view/web vendor=src/galvoscan_view/galvoscan_view/static/vendor
  command -v npm >/dev/null \
    || { echo "[setup] npm (Node.js) is needed to vendor three.js for the view page"; exit 1; }
  echo "[setup] vendoring three.js for the view page (npm ci)"
  (cd "$web" && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error) \
    || { echo "[setup] npm ci in $web failed"; exit 1; }
  local three=$web/node_modules/three
  rm -rf "$vendor"
  mkdir -p "$vendor"
  cp "$three/build/three.module.js" "$three/build/three.core.js" "$vendor/"
  cp "$three/LICENSE" "$vendor/three.LICENSE"
  # OrbitControls imports the bare name 'three', which a browser resolves only through an
  # import map (an inline script, which the page's Content-Security-Policy forbids): point
  # it at the file beside it instead.
  sed "s#from 'three';#from './three.module.js';#" \
    "$three/examples/jsm/controls/OrbitControls.js" >"$vendor/OrbitControls.js"
  if grep -q "from 'three'" "$vendor/OrbitControls.js"; then
    echo "[setup] OrbitControls.js still imports 'three' by name"; exit 1
  fi
  # the Foxglove client that draws a cloud of galvoscan view (tools/foxglove_client)
  echo "[setup] installing the Foxglove client (npm ci)"
  (cd tools/foxglove_client && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error) \
    || { echo "[setup] npm ci in tools/foxglove_client failed"; exit 1; }
}

for s in "$@"; do "step_$s"; done
