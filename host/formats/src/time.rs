//! UTC civil time from Unix seconds, without a time zone database (the reports' and pages'
//! times are UTC).

/// Unix seconds as `[year, month, day, hour, minute, second]` UTC, the proleptic Gregorian
/// calendar (Howard Hinnant's days-to-civil).
pub fn utc(unix_s: i64) -> [i64; 6] {
    let (days, rem) = (unix_s.div_euclid(86_400), unix_s.rem_euclid(86_400));
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    [y, m, d, rem / 3600, rem / 60 % 60, rem % 60]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against dates known by hand, a leap day and before 1970 among them.
    #[test]
    fn civil_dates() {
        assert_eq!(utc(0), [1970, 1, 1, 0, 0, 0]);
        assert_eq!(utc(951_782_400), [2000, 2, 29, 0, 0, 0]);
        assert_eq!(utc(1_700_000_000), [2023, 11, 14, 22, 13, 20]);
        assert_eq!(utc(-86_400), [1969, 12, 31, 0, 0, 0]);
    }
}
