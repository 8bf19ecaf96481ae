/*
 * json_fixture.h - reading the numbers of a parsed report (cJSON) in a
 * cmocka test: a missing or non-numeric field fails the test, naming it.
 * Header-only; include after cmocka.h and cJSON.h.
 */
#ifndef MR_TEST_JSON_FIXTURE_H
#define MR_TEST_JSON_FIXTURE_H

static inline double fx_json_number(const cJSON *o, const char *key)
{
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(o, key);
    if (!cJSON_IsNumber(v))
        fail_msg("no number \"%s\"", key);
    return v->valuedouble;
}

#endif
