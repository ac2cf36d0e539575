"""bcf.core.report: decoded export -> quality report.

`metrics` (PSNR and SSIM per mip and texture), `report_json` (report.json and its table), `html` (report.html),
`baselines` (conventional codecs scored the same way), `check` (the regression gate between two reports).
"""
