#!/usr/bin/env bash
# Install BranchRange's onboard daemon on a Debian/Ubuntu or JetPack companion computer, in 12 steps:
# system packages, service user, folders, venv, torch (CPU or CUDA), the project with its extras,
# weights, calibration, configuration, unit and udev files, systemd and udev reload, preflight.
# docs/onboard.md ("Installing") explains each step and its by-hand equivalent.
#
#   sudo deploy/install.sh                              # this machine, for real
#   deploy/install.sh --dry-run                         # print every step, change nothing
#   deploy/install.sh --prefix /tmp/br --no-preflight   # the whole tree under /tmp/br, no root needed
#
# Re-running is safe: the venv is reused, an edited configuration is kept (the new one is written
# beside it as onboard.toml.new), files already in place are rewritten with the same content.
# Exit status: 0 installed (and preflight passed), 1 a step failed, 2 bad options or an unusable machine.
set -euo pipefail

readonly SERVICE_USER=branchrange
readonly SERVICE_GROUPS=video,dialout
readonly UNIT_NAME=branchrange-daemon.service
readonly RULES_NAME=99-branchrange-cameras.rules
readonly CPU_TORCH_INDEX=https://download.pytorch.org/whl/cpu
readonly JETSON_UART=/dev/ttyTHS1
readonly PYTHON_IS_RECENT='import sys; sys.exit(sys.version_info < (3, 11))'  # tomllib
DEPLOY_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
readonly DEPLOY_DIR

usage() {
    cat <<'EOF'
usage: deploy/install.sh [options]

Install the onboard daemon: user, folders, venv, torch, extras, weights, calibration,
configuration, systemd unit, udev rules, then `branchrange preflight`.

options:
  --prefix DIR          install under DIR (default /): DIR/opt/branchrange, DIR/etc/branchrange,
                        DIR/var/lib/branchrange, DIR/etc/systemd/system, DIR/etc/udev/rules.d;
                        paths in the unit and the configuration point there. Not / : no user, no
                        system packages, no systemctl, no root needed
  --dry-run             print every step and its commands, change nothing
  --config FILE         onboard.toml (EMCStereo on CUDA) or onboard_cpu.toml (SGBM, CPU), or a path;
                        default: onboard.toml with a CUDA torch, onboard_cpu.toml with a CPU one
  --torch auto|cpu|cuda which torch build (default auto: CUDA with an NVIDIA driver on x86-64, or on
                        JetPack with --torch-spec; CPU otherwise)
  --torch-index URL     the index torch comes from (default: PyTorch's CPU index for a CPU build,
                        pip's own for a CUDA one); `default` means pip's configured index
  --torch-spec SPEC     what to install as torch: a requirement, a wheel file or its URL
                        (JetPack: a CUDA wheel built for JetPack 6 and CPython 3.11)
  --extras LIST         the project's extras (default ros,coco,onnx)
  --wheel-dir DIR       offline: every package from this folder of wheels (no index)
  --source DIR          the project to install (default: this script's checkout)
  --python PY           the interpreter the venv is made with (default: python3.11 or newer)
  --skip-pip            install nothing into the venv: it already holds the project (re-runs, tests)
  --weights-from DIR    copy the weights the configuration names from DIR
  --fetch-weights       download them (`emcstereo weights fetch`, checked by SHA-256)
  --calibration FILE    the camera's factory SN<serial>.conf: copied next to the configuration,
                        which then names it
  --set SECTION.KEY=VALUE
                        set one key of the configuration (a TOML value, repeatable),
                        e.g. --set 'mavlink.url="udpout:127.0.0.1:14550"'
  --no-systemd          write the unit and the rules, but call neither systemctl nor udevadm
  --no-preflight        end without `branchrange preflight` (no camera attached yet)
  --detect-root DIR     look for /etc/os-release, /etc/nv_tegra_release and the NVIDIA driver
                        under DIR (default /)
  -h, --help            this help
EOF
}

die() {  # die STATUS MESSAGE...: the reason on stderr, then exit
    local status=$1
    shift
    echo "install.sh: $*" >&2
    exit "$status"
}

need_value() {  # need_value OPTION ARGC: an option that takes a value must have one
    [[ $2 -ge 2 ]] || die 2 "$1 needs a value (see --help)"
}

PREFIX=/
DRY_RUN=0
CONFIG=""
TORCH=auto
TORCH_INDEX=""
TORCH_SPEC=""
EXTRAS=ros,coco,onnx
WHEEL_DIR=""
SOURCE=$(dirname "$DEPLOY_DIR")
PYTHON=""
SKIP_PIP=0
WEIGHTS_FROM=""
FETCH_WEIGHTS=0
CALIBRATION=""
SETS=()
SYSTEMD=1
PREFLIGHT=1
DETECT_ROOT=/

while [[ $# -gt 0 ]]; do
    case $1 in
        --prefix) need_value "$1" $#; PREFIX=$2; shift ;;
        --dry-run) DRY_RUN=1 ;;
        --config) need_value "$1" $#; CONFIG=$2; shift ;;
        --torch) need_value "$1" $#; TORCH=$2; shift ;;
        --torch-index) need_value "$1" $#; TORCH_INDEX=$2; shift ;;
        --torch-spec) need_value "$1" $#; TORCH_SPEC=$2; shift ;;
        --extras) need_value "$1" $#; EXTRAS=$2; shift ;;
        --wheel-dir) need_value "$1" $#; WHEEL_DIR=$2; shift ;;
        --source) need_value "$1" $#; SOURCE=$2; shift ;;
        --python) need_value "$1" $#; PYTHON=$2; shift ;;
        --skip-pip) SKIP_PIP=1 ;;
        --weights-from) need_value "$1" $#; WEIGHTS_FROM=$2; shift ;;
        --fetch-weights) FETCH_WEIGHTS=1 ;;
        --calibration) need_value "$1" $#; CALIBRATION=$2; shift ;;
        --set) need_value "$1" $#; SETS+=("$2"); shift ;;
        --no-systemd) SYSTEMD=0 ;;
        --no-preflight) PREFLIGHT=0 ;;
        --detect-root) need_value "$1" $#; DETECT_ROOT=$2; shift ;;
        -h | --help) usage; exit 0 ;;
        *) die 2 "unknown option $1 (see --help)" ;;
    esac
    shift
done

# ---------------------------------------------------------------- helpers

STEP=0
readonly STEPS=12

step() {  # step TITLE: the heading of the next step
    STEP=$((STEP + 1))
    printf '\n==> [%d/%d] %s\n' "$STEP" "$STEPS" "$1"
}

note() {
    printf '    %s\n' "$*"
}

shell_words() {  # shell_words WORD...: the words as a shell line, quoted only where a shell needs it
    local word line=""
    for word in "$@"; do
        if [[ $word =~ ^[A-Za-z0-9_./:=@%+,-]+$ ]]; then
            line+=" $word"
        elif [[ $word != *"'"* ]]; then
            line+=" '$word'"
        else
            line+=" $(printf '%q' "$word")"
        fi
    done
    printf '%s' "${line# }"
}

run() {  # run COMMAND...: print it, then run it unless --dry-run
    printf '    $ %s\n' "$(shell_words "$@")"
    [[ $DRY_RUN -eq 1 ]] || "$@"
}

toml_get() {  # toml_get FILE SECTION KEY: a one-line string value of [SECTION] KEY, unquoted ('' if absent)
    awk -v section="$2" -v key="$3" '
        /^[ \t]*\[/ { header = $0; gsub(/^[ \t]*\[|\][ \t]*(#.*)?$/, "", header); inside = (header == section); next }
        inside && $0 ~ "^[ \t]*" key "[ \t]*=" {
            value = $0; sub(/^[^=]*=[ \t]*"/, "", value); sub(/".*$/, "", value); print value; exit
        }' "$1"
}

toml_set() {  # toml_set FILE SECTION KEY VALUE: set [SECTION] KEY to the TOML VALUE in place, comments kept
    local edited
    edited=$(awk -v section="$2" -v key="$3" -v value="$4" '
        function put() { print key " = " value "  # set by deploy/install.sh"; done = 1 }
        /^[ \t]*\[/ {
            if (inside && !done) put()
            header = $0; gsub(/^[ \t]*\[|\][ \t]*(#.*)?$/, "", header); inside = (header == section)
        }
        inside && !done && $0 ~ "^[ \t]*" key "[ \t]*=" { put(); next }
        { print }
        END { if (!done) { if (!inside) print "\n[" section "]"; put() } }' "$1")
    printf '%s\n' "$edited" >"$1"
}

relocate() {  # relocate SOURCE DEST: copy a deploy file with /opt, /etc and /var/lib/branchrange under PREFIX
    sed -e "s#/opt/branchrange#${ROOT}opt/branchrange#g" \
        -e "s#/etc/branchrange#${ROOT}etc/branchrange#g" \
        -e "s#/var/lib/branchrange#${ROOT}var/lib/branchrange#g" "$1" >"$2"
}

# ---------------------------------------------------------------- options and the machine

ROOT=$(realpath -m "$PREFIX")
ROOT=${ROOT%/}/
readonly ROOT
OPT=${ROOT}opt/branchrange
ETC=${ROOT}etc/branchrange
STATE=${ROOT}var/lib/branchrange
UNIT_DIR=${ROOT}etc/systemd/system
UDEV_DIR=${ROOT}etc/udev/rules.d
VENV=$OPT/.venv
readonly OPT ETC STATE UNIT_DIR UDEV_DIR VENV
SYSTEM_INSTALL=0  # the machine's own /, as root: the only case that adds a user, chowns and calls systemctl
[[ $ROOT == / && $EUID -eq 0 ]] && SYSTEM_INSTALL=1
readonly SYSTEM_INSTALL

case $TORCH in auto | cpu | cuda) ;; *) die 2 "--torch $TORCH: expected auto, cpu or cuda" ;; esac
[[ -f $SOURCE/pyproject.toml ]] || die 2 "--source $SOURCE: no pyproject.toml there (the project's checkout)"
[[ -z $WHEEL_DIR || -d $WHEEL_DIR ]] || die 2 "--wheel-dir $WHEEL_DIR: no such folder"
[[ -z $WEIGHTS_FROM || -d $WEIGHTS_FROM ]] || die 2 "--weights-from $WEIGHTS_FROM: no such folder"
[[ -z $CALIBRATION || -f $CALIBRATION ]] || die 2 "--calibration $CALIBRATION: no such file"
[[ $EXTRAS =~ ^[a-z0-9,_-]*$ ]] || die 2 "--extras $EXTRAS: expected a comma-separated list such as ros,coco"
for assignment in "${SETS[@]}"; do
    [[ $assignment =~ ^[a-z_.]+\.[a-z0-9_]+=.+$ ]] || die 2 "--set $assignment: expected SECTION.KEY=VALUE"
done

# shellcheck disable=SC1091  # the machine's own file, read in a subshell
SYSTEM="$(. "$DETECT_ROOT/etc/os-release" 2>/dev/null && echo "${ID:-unknown} ${VERSION_ID:-}")" || SYSTEM=unknown
JETPACK=0
[[ -f $DETECT_ROOT/etc/nv_tegra_release ]] && JETPACK=1
NVIDIA_DRIVER=0
[[ -f $DETECT_ROOT/proc/driver/nvidia/version ]] && NVIDIA_DRIVER=1
if [[ $TORCH == auto ]]; then
    TORCH=cpu
    if [[ $JETPACK -eq 1 && -n $TORCH_SPEC ]] || [[ $JETPACK -eq 0 && $NVIDIA_DRIVER -eq 1 ]]; then TORCH=cuda; fi
fi
[[ $TORCH == cuda && $JETPACK -eq 1 && -z $TORCH_SPEC && -z $WHEEL_DIR ]] &&
    die 2 "a CUDA torch on JetPack needs --torch-spec WHEEL: no public index has one for JetPack 6 and" \
        "CPython 3.11 (see deploy/Dockerfile.jetson), or take --torch cpu"
PINNED_TORCH=$(grep -E '^torch==' "$DEPLOY_DIR/constraints.txt")
[[ -n $TORCH_SPEC ]] || TORCH_SPEC=$PINNED_TORCH
if [[ -z $TORCH_INDEX ]]; then
    TORCH_INDEX=default
    [[ $TORCH == cpu ]] && TORCH_INDEX=$CPU_TORCH_INDEX
fi

if [[ -z $CONFIG ]]; then
    CONFIG=onboard_cpu.toml
    [[ $TORCH == cuda ]] && CONFIG=onboard.toml
fi
[[ $CONFIG == */* ]] || CONFIG=$DEPLOY_DIR/$CONFIG
[[ -f $CONFIG ]] || die 2 "--config $CONFIG: no such file"
if [[ -z $PYTHON ]]; then
    for candidate in python3.11 python3.12 python3.13 python3; do
        if command -v "$candidate" >/dev/null && "$candidate" -c "$PYTHON_IS_RECENT"; then
            PYTHON=$candidate
            break
        fi
    done
    [[ -n $PYTHON ]] || die 2 "no CPython 3.11 or newer found (BranchRange reads TOML with tomllib): install" \
        "python3.11 and python3.11-venv (JetPack 6: from the deadsnakes PPA, see docs/onboard.md), or give --python"
fi
"$PYTHON" -c "$PYTHON_IS_RECENT" 2>/dev/null ||
    die 2 "--python $PYTHON: not a CPython 3.11 or newer"
PYTHON_VERSION=$("$PYTHON" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')

PIP_SOURCE=()  # where pip finds packages: the wheel folder offline, else its own configuration
[[ -n $WHEEL_DIR ]] && PIP_SOURCE=(--no-index --find-links "$WHEEL_DIR")
TORCH_FROM=("${PIP_SOURCE[@]}")
[[ -z $WHEEL_DIR && $TORCH_INDEX != default ]] && TORCH_FROM=(--index-url "$TORCH_INDEX")

echo "BranchRange install: system ${SYSTEM}$([[ $JETPACK -eq 1 ]] && echo ' (JetPack)'), $(uname -m)," \
    "NVIDIA driver $([[ $NVIDIA_DRIVER -eq 1 ]] && echo yes || echo no), torch $TORCH ($TORCH_SPEC)," \
    "config $(basename "$CONFIG"), python $PYTHON ($PYTHON_VERSION), prefix $ROOT" \
    "$([[ $DRY_RUN -eq 1 ]] && echo '(dry run)')"

WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT

# The configuration this install writes, made here (in $WORK) so that every step reads the final values:
# paths under the prefix, the schema beside it, the calibration given, the JetPack UART, every --set.
CANDIDATE=$WORK/onboard.toml
relocate "$CONFIG" "$CANDIDATE"
sed -i 's|^#:schema .*|#:schema config.schema.json|' "$CANDIDATE"
if [[ -n $CALIBRATION ]]; then
    CALIBRATION_DEST=$ETC/$(basename "$CALIBRATION")
    SETS=("camera.calibration=\"$CALIBRATION_DEST\"" "${SETS[@]}")
fi
if [[ $JETPACK -eq 1 && $(toml_get "$CANDIDATE" mavlink url) == /dev/ttyAMA0 ]]; then
    SETS=("mavlink.url=\"$JETSON_UART\"" "${SETS[@]}")  # the Raspberry Pi's UART name in onboard_cpu.toml
fi
for assignment in "${SETS[@]}"; do
    name=${assignment%%=*}
    toml_set "$CANDIDATE" "${name%.*}" "${name##*.}" "${assignment#*=}"
done
CONFIG_DEVICE=$(toml_get "$CANDIDATE" stereo device)
[[ $CONFIG_DEVICE == cuda && $TORCH == cpu ]] &&
    die 2 "$(basename "$CONFIG") runs the network on CUDA (stereo.device = \"cuda\") but this install takes a" \
        "CPU torch: the daemon would refuse to start; use --config onboard_cpu.toml, or a CUDA torch" \
        "(--torch cuda; on JetPack with --torch-spec)"
WEIGHTS_NAMED=$(toml_get "$CANDIDATE" stereo weights)

# ---------------------------------------------------------------- the steps

step "system packages: libusb for the cameras, the venv module"
SYSTEM_PACKAGES=(libusb-1.0-0 "python${PYTHON_VERSION}-venv")
if [[ $SYSTEM_INSTALL -eq 1 ]] && command -v apt-get >/dev/null; then
    MISSING=()
    for package in "${SYSTEM_PACKAGES[@]}"; do
        dpkg-query --show --showformat='${Status}' "$package" 2>/dev/null | grep --quiet 'ok installed' ||
            MISSING+=("$package")
    done
    if [[ ${#MISSING[@]} -gt 0 ]]; then  # offline, apt-get update fails: have them installed beforehand
        run apt-get update
        run apt-get install -y --no-install-recommends "${MISSING[@]}"
    else
        note "kept: ${SYSTEM_PACKAGES[*]} already installed"
    fi
else
    note "skipped: needs root on / with apt-get (prefix $ROOT);" \
        "have libusb-1.0-0 and python${PYTHON_VERSION}-venv installed"
fi

step "service user $SERVICE_USER (groups $SERVICE_GROUPS: the camera and the serial port)"
if [[ $SYSTEM_INSTALL -eq 0 ]]; then
    note "skipped: needs root and --prefix / (files stay owned by $(id -un))"
elif id "$SERVICE_USER" >/dev/null 2>&1; then
    run usermod --append --groups "$SERVICE_GROUPS" "$SERVICE_USER"
else
    run useradd --system --user-group --groups "$SERVICE_GROUPS" --no-create-home \
        --shell /usr/sbin/nologin "$SERVICE_USER"
fi

step "folders: $OPT, $ETC (configuration), $STATE (results)"
run install -d -m 0755 "$OPT" "$OPT/weights" "$UNIT_DIR" "$UDEV_DIR"
run install -d -m 0750 "$ETC" "$STATE"
if [[ $SYSTEM_INSTALL -eq 1 ]]; then
    run chown "root:$SERVICE_USER" "$ETC"
    run chown "$SERVICE_USER:$SERVICE_USER" "$STATE"
fi

step "venv: $VENV (the unit's ExecStart)"
if [[ -x $VENV/bin/python ]] && "$VENV/bin/python" -c "$PYTHON_IS_RECENT"; then
    note "kept: $VENV already holds a CPython 3.11 or newer"
else
    run "$PYTHON" -m venv "$VENV"
fi
VENV_PYTHON=$VENV/bin/python

step "torch: the $TORCH build ($TORCH_SPEC)"
CONSTRAINTS=$DEPLOY_DIR/constraints.txt
if [[ $TORCH_SPEC != "$PINNED_TORCH" ]]; then  # another torch: every pin but torch's
    CONSTRAINTS=$WORK/constraints-without-torch.txt
    grep -v '^torch==' "$DEPLOY_DIR/constraints.txt" >"$CONSTRAINTS"
fi
if [[ $SKIP_PIP -eq 1 ]]; then
    note "skipped (--skip-pip): the venv's own torch is used"
else
    run "$VENV_PYTHON" -m pip install --quiet -c "$CONSTRAINTS" "${TORCH_FROM[@]}" "$TORCH_SPEC"
fi
CUDA_CHECK='import sys, torch; sys.exit(torch.version.cuda is None)'
if [[ $CONFIG_DEVICE == cuda ]]; then
    note "$(basename "$CONFIG") runs on CUDA: the installed torch must be a CUDA build"
    run "$VENV_PYTHON" -c "$CUDA_CHECK" ||
        die 1 "the torch in $VENV is a CPU build but $(basename "$CONFIG") needs CUDA:" \
            "use --config onboard_cpu.toml or a CUDA torch"
fi

step "branchrange with extras [$EXTRAS], versions pinned by deploy/constraints.txt"
if [[ $SKIP_PIP -eq 1 ]]; then
    note "skipped (--skip-pip): the venv already holds the project"
else
    run "$VENV_PYTHON" -m pip install --quiet -c "$CONSTRAINTS" "${PIP_SOURCE[@]}" "${SOURCE}[$EXTRAS]"
fi

step "weights the configuration names"
if [[ -z $WEIGHTS_NAMED ]]; then
    note "none needed: $(basename "$CONFIG") names no stereo weights (the branch segmenter ships with the package)"
else
    WEIGHTS_FILE=$(basename "$WEIGHTS_NAMED")
    if [[ -n $WEIGHTS_FROM ]]; then
        [[ -f $WEIGHTS_FROM/$WEIGHTS_FILE ]] || die 2 "--weights-from $WEIGHTS_FROM: no $WEIGHTS_FILE there"
        run "$VENV/bin/emcstereo" weights verify "$WEIGHTS_FROM/$WEIGHTS_FILE" ||
            die 1 "$WEIGHTS_FROM/$WEIGHTS_FILE is not the released $WEIGHTS_FILE (SHA-256); nothing copied"
        run install -m 0644 "$WEIGHTS_FROM/$WEIGHTS_FILE" "$OPT/weights/$WEIGHTS_FILE"
    elif [[ $FETCH_WEIGHTS -eq 1 ]]; then
        run "$VENV/bin/emcstereo" weights fetch emcstereo-virtualtree --dest "$OPT/weights" --quiet
    elif [[ -f $OPT/weights/$WEIGHTS_FILE ]]; then
        note "kept: $OPT/weights/$WEIGHTS_FILE"
    else
        note "missing: $OPT/weights/$WEIGHTS_FILE;" \
            "give --weights-from DIR or --fetch-weights (preflight fails without it)"
    fi
fi

step "calibration: the camera's factory SN<serial>.conf"
if [[ -n $CALIBRATION ]]; then
    run install -m 0640 "$CALIBRATION" "$CALIBRATION_DEST"
elif [[ -n $(toml_get "$CANDIDATE" camera calibration) ]]; then
    note "none given: put the camera's file where camera.calibration says," \
        "$(toml_get "$CANDIDATE" camera calibration), or give --calibration FILE"
else
    note "none: camera.calibration is empty (an OAK or a replay: source brings its own)"
fi

step "configuration: $ETC/onboard.toml from $(basename "$CONFIG")"
for assignment in "${SETS[@]}"; do
    note "set ${assignment%%=*} = ${assignment#*=}"
done
if [[ -f $ETC/onboard.toml ]] && ! cmp -s "$CANDIDATE" "$ETC/onboard.toml"; then
    note "kept: $ETC/onboard.toml differs from this install's; the new one is $ETC/onboard.toml.new"
    run install -m 0640 "$CANDIDATE" "$ETC/onboard.toml.new"
else
    run install -m 0640 "$CANDIDATE" "$ETC/onboard.toml"
fi
if [[ $DRY_RUN -eq 1 ]]; then
    printf '    $ %s >%s\n' "$(shell_words "$VENV/bin/branchrange" config schema)" "$ETC/config.schema.json"
else
    "$VENV/bin/branchrange" config schema >"$WORK/config.schema.json" ||
        die 1 "$VENV cannot run branchrange (was the project installed? see the steps above)"
    run install -m 0644 "$WORK/config.schema.json" "$ETC/config.schema.json"
fi
if [[ $SYSTEM_INSTALL -eq 1 ]]; then  # readable by the service, by nobody else
    READABLE=("$ETC/onboard.toml" ${CALIBRATION:+"$CALIBRATION_DEST"})
    [[ -f $ETC/onboard.toml.new ]] && READABLE+=("$ETC/onboard.toml.new")
    run chown "root:$SERVICE_USER" "${READABLE[@]}"
fi
run "$VENV/bin/branchrange" config check --file-only "$ETC/onboard.toml" ||
    die 1 "$ETC/onboard.toml has problems (listed above): edit it and run the line above again"
# What the daemon's run needs from this machine (calibration, weights, a writable log …) may come later, e.g.
# a camera's SN*.conf copied after the install: listed now, checked again by preflight before arming.
run "$VENV/bin/branchrange" config check --for daemon "$ETC/onboard.toml" ||
    note "the daemon cannot start until what is listed above is in place (preflight checks it again)"

step "systemd unit and udev rules"
relocate "$DEPLOY_DIR/$UNIT_NAME" "$WORK/$UNIT_NAME"
run install -m 0644 "$WORK/$UNIT_NAME" "$UNIT_DIR/$UNIT_NAME"
run install -m 0644 "$DEPLOY_DIR/$RULES_NAME" "$UDEV_DIR/$RULES_NAME"
run install -m 0644 "$SOURCE/README.md" "$OPT/README.md"  # the unit's Documentation=

step "systemd and udev: reload, enable the daemon"
if [[ $SYSTEMD -eq 0 || $SYSTEM_INSTALL -eq 0 ]]; then
    REASON="prefix $ROOT, not root on /"
    [[ $SYSTEMD -eq 0 ]] && REASON=--no-systemd
    note "skipped ($REASON): files written, nothing reloaded"
else
    run udevadm control --reload
    run udevadm trigger --subsystem-match=video4linux --subsystem-match=usb --subsystem-match=hidraw
    run systemctl daemon-reload
    run systemctl enable "$UNIT_NAME"
fi

step "preflight: camera, calibration, weights, one frame, the autopilot (docs/preflight.md)"
PREFLIGHT_COMMAND=("$VENV/bin/branchrange" preflight --config "$ETC/onboard.toml")
[[ $SYSTEM_INSTALL -eq 1 ]] && PREFLIGHT_COMMAND=(runuser -u "$SERVICE_USER" -- "${PREFLIGHT_COMMAND[@]}")
if [[ $PREFLIGHT -eq 0 ]]; then
    note "skipped (--no-preflight); once the camera and the autopilot are connected:"
    note "$(shell_words "${PREFLIGHT_COMMAND[@]}")"
else
    if [[ $SYSTEMD -eq 1 && $SYSTEM_INSTALL -eq 1 ]] && systemctl is-active --quiet "$UNIT_NAME" 2>/dev/null; then
        run systemctl stop "$UNIT_NAME"  # it holds the camera and the serial port
    fi
    run "${PREFLIGHT_COMMAND[@]}" || die 1 "preflight failed (above): fix what it names, then run it again"
    [[ $SYSTEMD -eq 1 && $SYSTEM_INSTALL -eq 1 ]] && run systemctl restart "$UNIT_NAME"
fi

echo
echo "BranchRange installed under $ROOT$([[ $DRY_RUN -eq 1 ]] && echo ' (dry run: nothing changed)')"
