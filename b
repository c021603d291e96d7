Found 21 errors.
[*] 8 fixable with `--fix` (11 unsafe fixes available with `--fix --unsafe-fixes`).
benchmarks/cages_ab.py: PLW1510 `subprocess.run` without explicit `check` argument
benchmarks/doc_tables.py: FURB167 [*] Use of regular expression alias `re.S`
benchmarks/doc_tables.py: FURB167 [*] Use of regular expression alias `re.S`
benchmarks/doc_tables.py: ISC004 Unparenthesized implicit string concatenation in collection
benchmarks/doc_tables.py: ISC004 Unparenthesized implicit string concatenation in collection
benchmarks/doc_tables.py: ISC004 Unparenthesized implicit string concatenation in collection
benchmarks/doc_tables.py: ISC004 Unparenthesized implicit string concatenation in collection
benchmarks/doc_tables.py: ISC004 Unparenthesized implicit string concatenation in collection
benchmarks/doc_tables.py: ISC004 Unparenthesized implicit string concatenation in collection
benchmarks/doc_tables.py: RUF059 Unpacked variable `head` is never used
benchmarks/doc_tables.py: RUF100 [*] Unused `noqa` directive (non-enabled: `E731`)
benchmarks/doc_tables.py: RUF100 [*] Unused `noqa` directive (non-enabled: `E731`)
benchmarks/doc_tables.py: RUF100 [*] Unused `noqa` directive (non-enabled: `E731`)
benchmarks/doc_tables.py: UP034 [*] Avoid extraneous parentheses
tests/test_cagegen_nested.py: B017 Do not assert blind exception: `Exception`
tests/test_cagegen_nested.py: I001 [*] Import block is un-sorted or un-formatted
tests/test_cagegen_nested.py: I001 [*] Import block is un-sorted or un-formatted
tests/test_cagegen_nested.py: RUF059 Unpacked variable `N` is never used
tests/test_cagegen_nested.py: RUF059 Unpacked variable `Q` is never used
tests/test_cagegen_nested.py: RUF059 Unpacked variable `W` is never used
tests/test_cagegen_nested.py: RUF059 Unpacked variable `n2` is never used
