# tal: every target bootstraps first (venv + pinned wheels + colcon build; a fast no-op when unchanged).
SHELL := /bin/bash
ENV := source scripts/env.sh
SCENARIO ?= tour
PYTEST_ARGS ?=

.PHONY: bootstrap run test bench experiments datasets lint clean

bootstrap:
	@bash scripts/bootstrap.sh

run: bootstrap
	@$(ENV) && bash scripts/run_scenario.sh $(SCENARIO)

test: bootstrap
	@$(ENV) && python -m pytest $(PYTEST_ARGS)

bench: bootstrap
	@$(ENV) && python bench/bench_bridge.py && python bench/bench_wbc.py && python bench/bench_stance.py \
		&& python bench/bench_estimator.py && python bench/bench_bags.py && python bench/bench_vfa.py \
		&& python bench/bench_vfa_cnn.py && python bench/bench_vpa.py && python bench/bench_graph.py \
		&& python bench/report.py

datasets: bootstrap
	@$(ENV) && python -m tal_lab.datasets --out data --duration-s $(or $(DURATION),70)

experiments: bootstrap
	@$(ENV) && python -m tal_lab.swbc_experiments --out results/swbc \
		&& python -m tal_lab.stance_experiments --out results/stance \
		&& python -m tal_lab.estimation_experiments --out results/estimation \
		&& python -m tal_sim2real benchmark --out results/sim2real --data data/sim2real --count 30 --jobs 2 --out-of-library 3 \
		&& python -m tal_sim2real mujoco --out results/sim2real/mujoco --data data/sim2real/mujoco \
		&& python -m tal_lab.vital.eval_vfa --out results/vital && python -m tal_lab.vital.eval_vpa --out results/vital \
		&& python -m tal_lab.vital.vpa_open_loop --out results/vital \
		&& python -m tal_lab.vital.vital_experiments --out results/vital --jobs 2

lint: bootstrap
	@$(ENV) && ruff check . && ruff format --check .

clean:
	rm -rf ros2_ws/build ros2_ws/install ros2_ws/log ros2_ws/.tal-build.sha256
