"""The schema of ``field_prior.parquet`` (issue 34), declared beside
:mod:`heliocal.pipeline.artifacts.schemas`, which lists it among every artifact."""

from __future__ import annotations

from .table import ArtifactSchema, Column

__all__ = ["FIELD_PRIOR"]

C = Column

FIELD_PRIOR = ArtifactSchema(
    name="field_prior",
    filename="field_prior.parquet",
    producer="fit-coarse",
    sort_by=("kinematic_type", "actuator_type", "geometry_source", "preset", "parameter_index"),
    description="The field's empirical-Bayes prior of the coarse parameters (`fit-coarse --prior "
                "field`; heliocal.pipeline.models.field_prior says how): per kinematic type, "
                "actuator type, geometry source and preset, each parameter's typical deviation "
                "from the nominal value over the well-determined heliostats (robust location and "
                "scale), and the expected error of the field-prior geometry that a heliostat "
                "without training rows gets. Rows of parameters without enough well-determined "
                "heliostats have no `scale` (their fits keep the default prior). With "
                "`--prior-from` the other work directory's prior, as it was used.",
    columns=(
        C("kinematic_type", "string", "", "Kinematic type of the group."),
        C("actuator_type", "string", "", "Actuator type of the group."),
        C("geometry_source", "string", "", "`properties` (heliostats with a properties file) or "
          "`default` (ingest's default geometry)."),
        C("preset", "string", "", "The preset whose fits estimate the prior and which it is "
          "given to."),
        C("parameter_index", "int64", "", "Position in the 28-parameter vector."),
        C("parameter", "string", "", "Parameter name."),
        C("unit", "string", "", "Unit of `mean` and `scale`: rad, m, or 1 (increments, relative "
          "to the nominal value)."),
        C("mean", "float64", "", "Typical deviation from the nominal value (median over the "
          "well-determined heliostats; 0 without a field prior)."),
        C("scale", "float64", "", "Prior sigma a heliostat's fit gets (the field's spread "
          "without the fits' noise, plus the median's uncertainty); missing: default prior.",
          nullable=True),
        C("n_heliostats", "int64", "", "Well-determined heliostats that estimate it."),
        C("noise_mrad", "float64", "mrad", "The measurements' noise the prior is weighed "
          "against (median over the estimating fits of their RMS data residual per component): "
          "a fit's prior rows are `(p - mean) / (scale / noise_mrad)`, as its data rows are "
          "unweighted mrad (missing: 1 mrad).", nullable=True),
        C("spatial", "bool", "", "True where the prior mean is the nearest heliostats' "
          "(`--prior field+spatial`, only where that reduces the spread)."),
        C("expected_error_mrad", "float64", "mrad", "The group's field-prior geometry (nominal "
          "plus the mean of its first preset): median over the group's heliostats of its mean "
          "test error, each with a prior from the other heliostats; what a heliostat without "
          "training rows is expected to get (missing: no heliostat with test rows).",
          nullable=True),
        C("nominal_error_mrad", "float64", "mrad", "The same median for the nominal geometry.",
          nullable=True),
        C("n_evaluated", "int64", "", "Heliostats of the group with test rows behind the two "
          "medians."),
    ),
)
