"""The report: host-side reading of what a run or a fit wrote. Its records (`records.py`:
`metrics.jsonl`, appended whole, and the statistics over it), the report files made of them
(`report.py`: `fig2.png`, `table.md`, `findings.md`; `report_plots`, `plot_limits`), the seeds of
several runs pooled into one report (`merge`), the paper's claims checked on them (`findings`,
`findings_objects`, `protocol`), reconstruction figures of given learners (`figures`), and an
offline fit's records and reports (`offline`).

Imports `bulbjax.config` (config.json read back), from the epoch's face only what the probes
regress (`probe_targets`), and the layers below; never `bulbjax.run`, which uses this face."""

from bulbjax.report.figures import FigureConfig, boxes_figure, recon_figure, reconstructions, seed_params, spair_names
from bulbjax.report.merge import merge_seeds, run_records
from bulbjax.report.offline import records_of, summary_line, write_outputs
from bulbjax.report.protocol import probe_protocol_table
from bulbjax.report.records import (append_whole, band, ci90, ends_mid_line, epoch_records, last_returns, metrics_path,
                                    nanmean, probed, read_jsonl, scalars, write_jsonl, write_jsonl_atomic)
from bulbjax.report.report import files_written, is_offline, redraw, rl_compare, write_reports

__all__ = ["FigureConfig", "boxes_figure", "recon_figure", "reconstructions", "seed_params", "spair_names",
           "records_of", "summary_line", "write_outputs", "probe_protocol_table", "append_whole", "band", "ci90",
           "ends_mid_line", "epoch_records", "last_returns", "metrics_path", "nanmean", "probed", "read_jsonl",
           "scalars", "write_jsonl", "write_jsonl_atomic", "files_written", "is_offline", "merge_seeds", "run_records",
           "redraw", "rl_compare", "write_reports"]
