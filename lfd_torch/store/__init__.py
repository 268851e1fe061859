"""Results store: run manifests, atomic writes, results tables and sweep collection.

Notation:
    row          one (experiment, shape, method, fold, seed, trajectory) -- :data:`KEY_COLUMNS` -- with metric
                 columns (E1, E2, E3, DTWD, ... in the data's units) and provenance columns beside
    provenance   config_hash, seed, package_version, git_sha -- :data:`PROVENANCE_COLUMNS`
    manifest     dict from :func:`run_manifest`: provenance plus python/torch versions and a UTC timestamp
    part         one job's ``results.parquet`` inside a sweep directory

Typical job::

    manifest = run_manifest(cfg, seed=cfg.seed)
    write_table(rows, Path(output_dir) / "results.parquet", manifest=manifest)

and after the sweep::

    table = collect("multirun/2024-05-21/10-00-00", save_to="results/tables/lasa.parquet")

Every file is written atomically (:func:`atomic_path`, :func:`atomic_write`): readers never see a partial file.
The command line ``python -m lfd_torch.store.collect SWEEP_DIR --out FILE`` wraps :func:`collect`.
The experiment scripts check their Hydra configuration before fitting with :mod:`.config_checks` (errors name the
key), and set up each job with :func:`prepare_job`.
"""

from lfd_torch.store.atomic import atomic_path, atomic_save, atomic_write, is_temp_file
from lfd_torch.store.manifest import (
    DEFAULT_HASH_EXCLUDE,
    MANIFEST_FIELDS,
    canonical_json,
    config_hash,
    git_sha,
    run_manifest,
)
from lfd_torch.store.job import JobContext, prepare_job
from lfd_torch.store.staging import staged_outputs, staged_results
from lfd_torch.store.sweep import PartialSweepWarning, collect, find_parts, finished_part, unfinished_jobs
from lfd_torch.store.table import (
    KEY_COLUMNS,
    PROVENANCE_COLUMNS,
    REQUIRED_COLUMNS,
    read_manifest,
    read_table,
    validate_table,
    write_table,
)

__all__ = [
    "staged_outputs",
    "staged_results",
    "JobContext",
    "prepare_job",
    "atomic_path",
    "atomic_write",
    "is_temp_file",
    "canonical_json",
    "config_hash",
    "git_sha",
    "run_manifest",
    "MANIFEST_FIELDS",
    "DEFAULT_HASH_EXCLUDE",
    "KEY_COLUMNS",
    "PROVENANCE_COLUMNS",
    "REQUIRED_COLUMNS",
    "write_table",
    "read_table",
    "read_manifest",
    "validate_table",
    "collect",
    "find_parts",
    "finished_part",
    "unfinished_jobs",
    "PartialSweepWarning",
]
