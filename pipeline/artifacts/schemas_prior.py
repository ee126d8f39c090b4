"""The schema of ``field_prior.parquet`` (issue 34) and the field prior's columns of
``coarse_params.parquet``, declared beside :mod:`heliocal.pipeline.artifacts.schemas`, which lists
them among every artifact."""

from __future__ import annotations

from .table import ArtifactSchema, Column

__all__ = ["COARSE_PRIOR_COLUMNS", "FIELD_PRIOR"]

C = Column

#: The last columns of coarse_params.parquet: the field prior a fit was given and how much the
#: fit leans on it (docs/field_prior.md, "Shrinkage").
COARSE_PRIOR_COLUMNS = (
    C("prior_mean", "float64", "", "The prior mean this fit was given (in the parameter's "
      "unit): the nominal value moved by the field prior's mean of the heliostat's leave-out "
      "fold (field_prior.parquet holds the whole sample's), or the nominal value where the "
      "field prior does not cover the parameter (the default prior); missing where the fit "
      "had no field prior at all, and on fixed parameters.", nullable=True),
    C("prior_sigma", "float64", "", "The prior sigma this fit was given (the parameter's "
      "unit): its fold's field prior scale, or PRIOR_SIGMA where the field prior does not "
      "cover the parameter; missing like `prior_mean`.", nullable=True),
    C("prior_shrinkage", "float64", "1", "How much the fit of the parameter leans on its "
      "prior: `[H^-1]_jj [H_prior]_jj` of the fit's last Gauss-Newton system `H = H_data + "
      "H_prior` (the posterior variance over the prior variance, the derivative of `fitted` "
      "by `prior_mean`; 0: the data alone fix it, 1: the data say nothing about it); "
      "missing like `prior_mean`.", nullable=True),
    C("own_noise_mrad", "float64", "mrad", "The heliostat's own measurement noise per residual "
      "component, estimated from its fit under the field's noise (moderated toward the "
      "field's; heliocal.pipeline.models.prior_noise); repeated on each row of a fit with a "
      "field prior, missing elsewhere.", nullable=True),
    C("prior_noise_mrad", "float64", "mrad", "The noise the fit's field prior was weighed "
      "against (its rows `(p - prior_mean) / (prior_sigma / prior_noise_mrad)`): "
      "`own_noise_mrad` where that is more than 1.25x below field_prior.parquet's `noise_mrad` "
      "(the fit was solved again under it), that `noise_mrad` elsewhere; missing like "
      "`own_noise_mrad`.", nullable=True),
    C("prior_field_noise_mrad", "float64", "mrad", "The field's noise this parameter's field "
      "prior was first weighed against (the median noise of the sample fits of the "
      "heliostat's leave-out fold; field_prior.parquet's `noise_mrad` is the whole sample's), "
      "before any second solve under `own_noise_mrad`; on the parameters whose prior is the "
      "field's, missing on those that keep the default prior and like `prior_mean`. With "
      "`prior_mean` and `prior_sigma` it gives back the prior the fit was given (the sweep's "
      "training-size study refits under it).", nullable=True),
)

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
