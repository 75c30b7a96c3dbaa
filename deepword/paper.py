"""The DeepWORD paper's published numbers (Wu et al.), in one place: every report, table and benchmark that
sets our figures beside the paper's reads them here.

Only what could be checked against the paper is transcribed: Table 3's accuracies and the embedded-DSP
latency of Tables 1-2. The paper does not say whether Table 3's accuracy is per wheel or per image."""

TABLE3_ACCURACY = {  # percent, per test subset
    "logic": {"easy": 92.91, "hard": 71.83, "mixed": 79.90},
    "deepword": {"easy": 99.17, "hard": 94.35, "mixed": 95.14},
}
TABLE3_LABELS = {"logic": "logic model (paper)", "deepword": "DeepWORD (paper)"}

DSP_LATENCY = {"ms_per_img_b1": 3.2, "ms_per_10img_b10": 13.1}  # DeepWORD on an embedded DSP
