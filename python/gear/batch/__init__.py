"""`gear batch`: many scenes, each the whole pipeline as one Ray task (docs/batch.md).

- `scenes`: which scenes a batch holds (a folder of scene folders or a list file).
- `outcome`: one scene's result row, kept in its run folder as `batch.json`.
- `plan`: which scenes run, and which an earlier batch settled (`--resume`).
- `task`: one scene's pipeline (train, export, eval) inside a Ray worker.
- `scheduler`: submits the tasks with their resources and retries, and collects the outcomes.
- `progress`: the batch's progress bar and the line per finished scene.
- `summary`: `summary.csv` and `summary.md` over every scene.
"""
