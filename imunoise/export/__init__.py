"""Files written from analysis results: the Kalibr IMU noise YAML, the self-contained HTML
report with its SVG plots, the text report, and atomic writing of any of them."""
