# Two commands on a fresh machine: `make run` and `make test`. Each sets up what it needs:
# the virtual environment, the pinned dependencies, this package, and a local tf2_msgs.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
EGO    := $(VENV)/bin/ego-motion
READY  := $(VENV)/.ready
OUT    ?= out

.PHONY: setup run test bench clean default-bag

setup: $(READY)

TF2_SRC := $(wildcard resource/tf2_msgs/*.sh resource/tf2_msgs/*.txt resource/tf2_msgs/*.xml resource/tf2_msgs/msg/*.msg)

NATIVE_SRC := pyproject.toml $(wildcard camera_pose_nodes/native/*.cpp arbiter_node/native/*.cpp)

$(READY): requirements.txt setup.py setup.cfg $(TF2_SRC) $(NATIVE_SRC)
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade-strategy only-if-needed -r requirements.txt
	@# Builds the native kernel (camera_pose_nodes/native) with the pybind11 and Eigen just
	@# installed. --no-use-pep517: `setup.py develop`, which puts the console scripts where
	@# setup.cfg says (lib/<package>); with pyproject.toml pip would otherwise install an
	@# editable wheel, scripts in bin/.
	$(PY) -m pip install --quiet --no-deps --no-build-isolation --no-use-pep517 -e .
	@# Returns at once when the venv already has a tf2_msgs built from these sources.
	bash resource/tf2_msgs/build_tf2_msgs.sh $(VENV)
	@# setup.cfg puts console scripts where `ros2 run` looks (lib/<package>); put the CLI on the venv's PATH too.
	ln -sf ../lib/multicam_ego_motion/ego-motion $(EGO)
	@$(PY) -c 'import rclpy, cv2, filterpy, mcap, tf2_msgs.msg; from camera_pose_nodes import kernel; print("environment ready:", cv2.__version__, "quarter kernel:", kernel.selected())'
	@touch $@

run: $(READY)
	rm -rf $(OUT)/default
	$(EGO) replay bags/default --out $(OUT)/default

test: $(READY)
	$(PY) -m pytest test

bench: $(READY)
	rm -rf $(OUT)/bench
	$(EGO) bench bags/default --out $(OUT)/bench

# Regenerates the committed default bag (deterministic for the seed): the full 25 m loop in
# 20 s at 8 Hz, 320x240 (fx = 200), four cameras; about 22 MB with zstd (limit 25 MB).
default-bag: $(READY)
	rm -rf bags/default
	$(EGO) generate --scenario loop --duration 20 --rate 8 --width 320 --height 240 --seed 7 --out bags/default --rig-out config/rig_default.yaml

clean:
	rm -rf $(VENV) build install log $(OUT)
