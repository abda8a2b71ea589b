# Sums CubeCL's per-kernel profile lines ("| 1.23ms | Name") by kernel name, in ms. The summary
# tables CubeCL also logs ("| name | 1.2ms | 42 | 5 % |") and "not measured" lines are skipped.
$1 == "|" && $2 ~ /^[0-9.]+(ns|µs|ms|s)$/ && $3 == "|" {
  d = $2; n = $0; sub(/^\|[^|]*\| /, "", n)
  v = d + 0
  if (d ~ /µs$/) v /= 1000; else if (d ~ /ns$/) v /= 1e6; else if (d ~ /ms$/) v = v; else v *= 1000
  s[n] += v; c[n]++; tot += v; cnt++
}
END { printf "total %.1f ms over %d kernels\n", tot, cnt; for (k in s) printf "%10.2f ms %8d %s\n", s[k], c[k], k | "sort -rn" }
