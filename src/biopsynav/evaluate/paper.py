"""The reference figures of Mendizabal, Tagliabue et al. 2019 (section 3, Tables 1 and 2)."""

from __future__ import annotations

#: Table 1: mean norm error over the 200 test samples, mm; prediction time, ms; training, min
PAPER_TABLE1 = {
    "mean_e_mm": 0.052, "std_e_mm": 0.050, "max_e_mm": 0.266,
    "predict_mean_ms": 3.14, "predict_std_ms": 0.56, "train_min": 278.0,
    "max_disp_mm": 79.09, "n_elements": 2174, "n_train": 800, "n_test": 200,
}

#: FE solve time of the paper's data generation (SOFA), ms
PAPER_FE_MS = 407.7
PAPER_FE_STD_MS = 64.0

_NAN = None
#: Table 2 on the CIRS phantom (TRE, mm): rows lesions 1 ... 10, columns D10 ... D30
PAPER_TABLE2 = {
    "net": [
        [_NAN, 1.936, 2.002, 1.506, 3.053],
        [3.211, 2.905, 4.068, _NAN, 4.137],
        [2.032, _NAN, 4.709, 7.134, 10.90],
        [0.505, 2.225, 5.313, 5.903, _NAN],
        [0.932, 2.768, 3.454, _NAN, 4.893],
        [3.923, 6.349, 5.625, _NAN, 6.724],
        [3.454, 3.864, 4.543, 6.710, _NAN],
        [2.422, 3.261, 4.320, 5.136, _NAN],
        [_NAN, 3.928, 4.214, 4.578, 4.858],
        [5.529, 3.272, 3.940, 4.846, _NAN],
    ],
    "fem": [
        [_NAN, 1.326, 2.151, 2.075, 3.759],
        [1.956, 2.738, 3.945, _NAN, 4.025],
        [1.595, _NAN, 4.748, 7.044, 10.932],
        [0.755, 1.991, 4.544, 5.120, _NAN],
        [1.029, 2.863, 3.330, _NAN, 4.541],
        [2.579, 3.409, 2.871, _NAN, 2.337],
        [2.605, 3.219, 4.095, 6.750, _NAN],
        [2.695, 2.748, 4.321, 5.411, _NAN],
        [_NAN, 2.745, 2.497, 2.510, 4.193],
        [2.916, 2.542, 3.015, 3.868, _NAN],
    ],
}

#: the paper's column means (D10 ... D30) and its largest row means, mm
PAPER_TABLE2_COL_MEAN = {"net": [2.751, 3.390, 4.219, 5.116, 5.761],
                         "fem": [2.016, 2.620, 3.552, 4.682, 4.964]}
PAPER_TABLE2_MAX_ROW_MEAN = {"net": 6.194, "fem": 6.080}
