"""Metadata that every exported PRML2 ONNX model carries (torch-free; read by the runtime).

The exporter stores :class:`ModelMetadata` as JSON under the ONNX ``metadata_props`` key
``"prml2"``. The graph takes the raw onboard window in SI units (normalisation is inside
the graph; the statistics are repeated here for inspection) and returns the model's
z mean and variance for the L - H decoder steps *before* the physics guard: the guard runs
in NumPy (``prml2_edge.guard``) so the runtime can set the friction coefficient.

Graph contract: input ``onboard`` float32 (1, L, 9); outputs ``z_mean`` and ``z_var``
float32 (1, R, 5), ``z_var > 0``, for the newest R = ``output_rows`` decoder steps (None: all
L - H of them). The streaming runtime consumes only the newest row, so ``prml2 export`` writes
R = 1 by default: the last decoder layer then computes one query row instead of L - H.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

from prml2_edge import schema
from prml2_edge.errors import ModelError, reject_unknown_keys

METADATA_KEY = "prml2"
FORMAT = "prml2-onnx/1"
INPUT_NAME = "onboard"
OUTPUT_NAMES = ("z_mean", "z_var")


def guard_limits() -> dict:
    return {
        "v_max_mps": schema.V_MAX_MPS,
        "omega_max_radps": schema.OMEGA_MAX_RADPS,
        "a_max_dry_mps2": schema.A_MAX_DRY_MPS2,
        "a_max_low_mu_mps2": schema.A_MAX_LOW_MU_MPS2,
        "low_mu_threshold": schema.LOW_MU_THRESHOLD,
    }


@dataclass(frozen=True)
class ModelMetadata:
    version: str  # prml2_edge version that exported the model
    preset: str  # "paper" | "edge" | "tiny" | baseline name
    norm_mean: list[float]  # (9,) onboard normalisation, SI units, canonical order
    norm_std: list[float]  # (9,)
    dataset_fingerprint: str
    config: dict = field(default_factory=dict)  # model hyper-parameters
    ekf_process_noise: list[list[float]] | None = None  # Q (8, 8) the model was trained/tuned with
    training: dict = field(default_factory=dict)  # epochs, finetune, seed, ...
    format: str = FORMAT
    signal_names: list[str] = field(default_factory=lambda: list(schema.SIGNAL_NAMES))
    signal_units: list[str] = field(default_factory=lambda: [s.unit for s in schema.SIGNALS])
    state_names: list[str] = field(default_factory=lambda: list(schema.STATE_NAMES))
    L: int = schema.WINDOW_LEN
    H: int = schema.ENCODER_LEN
    input_name: str = INPUT_NAME
    output_names: list[str] = field(default_factory=lambda: list(OUTPUT_NAMES))
    guard_in_graph: bool = False
    guard: dict = field(default_factory=guard_limits)
    schema_hash: str = schema.SCHEMA_HASH
    output_rows: int | None = None  # decoder steps the graph returns, the newest ones (None: all L - H)
    # the model's slow error measured on validation (evaluation/error_model.py): {"var_inflation": [5], ...}
    error_model: dict | None = None

    @property
    def rows(self) -> int:
        """Rows of ``z_mean``/``z_var``: ``output_rows``, or L - H when the graph returns every decoder step."""
        return int(self.output_rows) if self.output_rows is not None else int(self.L - self.H)

    @property
    def reads_debiased_cues(self) -> bool:
        """Whether the model was trained on a_y and steering less the car's offsets (``cue_debiased_inputs``): the
        runtime then feeds it each row less its cue estimator's offsets."""
        return bool(self.config.get("cue_debiased_inputs", False))

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str, source: str = "model") -> ModelMetadata:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelError(f"{source}: PRML2 metadata is not valid JSON ({exc})") from exc
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ModelError(f"{source}: not a PRML2 model (metadata format {data.get('format')!r}, want {FORMAT!r})")
        reject_unknown_keys(data, cls.__dataclass_fields__, "{source}: unknown PRML2 metadata key {key}; re-export "
                            "with this version", ModelError, source=source)
        try:
            return cls(**data)
        except TypeError as exc:
            raise ModelError(f"{source}: incomplete PRML2 metadata ({exc})") from exc

    def check_schema(self, source: str = "model") -> None:
        """Refuse a model built for another signal layout, saying what differs."""
        if self.signal_names != list(schema.SIGNAL_NAMES):
            diff = [f"#{i}: model {a!r} vs runtime {b!r}"
                    for i, (a, b) in enumerate(zip(self.signal_names, schema.SIGNAL_NAMES, strict=False)) if a != b]
            raise ModelError(f"{source}: signal order differs from this runtime ({'; '.join(diff[:3]) or 'length'})")
        if self.signal_units != [s.unit for s in schema.SIGNALS]:
            raise ModelError(f"{source}: signal units differ from this runtime ({self.signal_units})")
        if self.state_names != list(schema.STATE_NAMES):
            raise ModelError(f"{source}: state order differs from this runtime ({self.state_names})")
        if len(self.norm_mean) != schema.NUM_SIGNALS or len(self.norm_std) != schema.NUM_SIGNALS:
            raise ModelError(f"{source}: normalisation statistics have the wrong length")
        if not (0 < self.H < self.L):
            raise ModelError(f"{source}: bad window geometry L={self.L}, H={self.H}")
        if not (isinstance(self.rows, int) and 1 <= self.rows <= self.L - self.H):
            raise ModelError(f"{source}: output_rows={self.output_rows} outside [1, L - H = {self.L - self.H}]")
        if self.schema_hash != schema.SCHEMA_HASH:
            raise ModelError(
                f"{source}: schema hash {self.schema_hash} differs from this runtime's {schema.SCHEMA_HASH}; "
                "re-export the model with this version"
            )
